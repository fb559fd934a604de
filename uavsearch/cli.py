"""The `uavsearch` command: every subcommand is wired here; each one's work lives in its module."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import __version__
from .errors import UavsearchError


# --------------------------------------------------------------------------------------------------
# scene


def _scene_from_args(args):
    from .world.scene import generate_scene, load_scene
    from .world.settings import SETTINGS

    if args.scene_file:
        return load_scene(args.scene_file)
    if args.occupied_cells is not None:
        k = args.occupied_cells
    else:
        if args.setting not in SETTINGS:
            raise UavsearchError(f"unknown setting {args.setting}; valid: {sorted(SETTINGS)} (or use --occupied-cells K)")
        k = SETTINGS[args.setting]
    return generate_scene(args.seed, k)


def _cmd_scene_show(args) -> int:
    from .search.config import SearchConfig
    from .search.views import TeleportVehicle
    from .viz import scene_show_figure

    spec = _scene_from_args(args)
    config = SearchConfig(altitude_m=args.altitude)
    with TeleportVehicle(spec, config) as vehicle:
        view = vehicle.capture([0.0, 0.0, config.altitude_m])
    out = scene_show_figure(spec, view, config.grid, config.intrinsics, args.out)
    occupied = [int(i) for i in spec.occupancy_array().nonzero()[0]]
    print(f"scene seed {spec.seed}: occupied cells {occupied}; wrote {out}")
    return 0


def _cmd_scene_save(args) -> int:
    from .world.scene import save_scene

    spec = _scene_from_args(args)
    try:
        save_scene(spec, args.out)
    except OSError as e:
        raise UavsearchError(f"cannot write {args.out}: {e.strerror or e}") from None
    print(f"wrote {args.out}")
    return 0


def _add_scene_parser(sub) -> None:
    scene = sub.add_parser("scene", help="generate, save and look at procedural city scenes")
    ssub = scene.add_subparsers(dest="scene_cmd", required=True, metavar="{show,save}")

    def common(p):
        p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
        p.add_argument("--setting", type=int, default=2, help="paper setting 1|2|3 = 2|5|10 occupied cells (default 2)")
        p.add_argument("--occupied-cells", type=int, default=None, metavar="K", help="any K in 0..100 instead of --setting")
        p.add_argument("--scene", dest="scene_file", default=None, metavar="JSON", help="load a saved scene spec instead")

    show = ssub.add_parser("show", help="PNG: the start view with the grid and occupied cells, beside a top-down map")
    common(show)
    show.add_argument("--altitude", type=float, default=70.0, help="camera altitude in m (default 70)")
    show.add_argument("--out", required=True, help="output PNG")
    show.set_defaults(func=_cmd_scene_show)

    save = ssub.add_parser("save", help="write the scene spec as JSON")
    common(save)
    save.add_argument("--out", required=True, help="output JSON")
    save.set_defaults(func=_cmd_scene_save)


# --------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uavsearch",
        description="Flight-dynamics-realistic MAVLink UAV testbed for active object search.",
    )
    parser.add_argument("--version", action="version", version=f"uavsearch {__version__}")
    sub = parser.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    _add_scene_parser(sub)
    from .flight.sitl import add_sitl_parser

    add_sitl_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UavsearchError as e:
        print(f"uavsearch: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("uavsearch: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
