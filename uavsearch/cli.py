"""The `uavsearch` command: every subcommand is wired here; each one's work lives in its module.

Imports of the subcommands' modules are lazy (inside the handlers) on purpose, measured on a shared
2-core machine: `uavsearch --help` takes 0.03-0.05 s (sitl's and mission's parsers are built only when named: the
autopilot, pymavlink and numpy cost 0.3 s); the scene modules (pydantic + OpenCV: world.scene, and
search.config / search.views / viz, which import it) would add 0.3-0.45 s, and torch (replay, the train /
eval groups; `fly` imports it once its vehicle process is starting) 2-5 s more. Nothing a subcommand imports ever
imports this module back.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
from pathlib import Path

from . import __version__
from .errors import UavsearchError, run_command, sigterm_as_interrupt


# --------------------------------------------------------------------------------------------------
# scene


def _scene_from_args(args):
    # lazy: world.scene costs --help 0.3-0.45 s (pydantic + OpenCV)
    from .world.scene import load_scene
    from .world.settings import setting_params

    if args.scene_file:
        return load_scene(args.scene_file)
    family = setting_params(args.setting)
    if args.occupied_cells is not None:  # the setting's scene parameters with another K
        family = family.model_copy(update={"k": args.occupied_cells})
    return family.scene(args.seed)


def _cmd_scene_show(args) -> int:
    # lazy: these import world.scene (see _scene_from_args)
    from .search.config import SearchConfig
    from .search.views import TeleportVehicle
    from .viz import scene_show_figure

    spec = _scene_from_args(args)
    config = SearchConfig(altitude_m=args.altitude, grid=spec.grid)
    with TeleportVehicle(spec, config) as vehicle:
        view = vehicle.capture([0.0, 0.0, config.altitude_m])
    out = scene_show_figure(spec, view, config.grid, config.intrinsics, args.out)
    occupied = [int(i) for i in spec.occupancy_array().nonzero()[0]]
    print(f"scene seed {spec.seed}: occupied cells {occupied}; wrote {out}")
    return 0


def _cmd_scene_save(args) -> int:
    # lazy: see _scene_from_args
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
        p.add_argument("--setting", default="2", help="paper setting 1|2|3 = 2|5|10 occupied cells, or a scene family: "
                       "wide (30 x 30 cells, people in groups), wide-uniform (default 2)")
        p.add_argument("--occupied-cells", type=int, default=None, metavar="K",
                       help="any K (0..cells of the setting's grid) instead of the setting's")
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
# fly / replay (uavsearch/fly/mission_controller.py, uavsearch/replay/replay.py)


def _cmd_fly(args) -> int:
    # lazy: pydantic, pymavlink, OpenCV; torch (2-5 s) is imported by fly() once the vehicle is starting, so
    # the mission is read without the agent registry (fly checks it then)
    from .fly.missions import FLY_MISSION, load_mission
    from .fly.mission_controller import VEHICLE_LOST, disk_full, fly, format_maps
    from .fly.scene_baselines import SceneComparison

    mission = load_mission(args.mission or FLY_MISSION, check_registry=False)
    mission = mission.with_overrides(check_registry=False, **{"scene.seed": args.scene, "flight.speed": args.speed})
    team = {k: v for k, v in (("vehicles", args.vehicles), ("mission_time_s", args.mission_time)) if v is not None}
    if team:  # the mission's validation says what its method can fly
        mission = mission.with_team(**team)
    # what the flight bought: other searches of its scene, computed beside the flight once the scene is known
    comparison = None if args.no_compare else SceneComparison(mission)
    try:
        _check_fly_ports(args)
        with sigterm_as_interrupt():  # SIGTERM lands like Ctrl-C and writes the summary; a second ends at once
            r = fly(mission, connect=args.connect, out=args.out, gcs_port=args.gcs_port, api_port=args.api_port,
                    progress=lambda line: print(line, flush=True),
                    on_scene=comparison.start if comparison is not None else None)
    except OSError as e:
        full = disk_full(Path(e.filename).parent if e.filename else Path(args.out or "."), e)
        if full is None:
            raise
        raise UavsearchError(full) from None
    if r.status.startswith((VEHICLE_LOST, "failed: no space")):  # one line: nothing more is worth showing
        print(f"uavsearch fly: {r.status.removeprefix('failed: ')}; the flight log so far: {r.run_dir}",
              file=sys.stderr)
        return 1
    print()
    if r.fused is not None:
        print(format_maps(r.fused, r.labels, mission.search_config().grid.n))
    sim = f"{r.sim_time_s:.1f} s" if r.sim_time_s is not None else "n/a"
    acc = f"{r.acc:.3f}" if r.acc is not None else "n/a"
    f1 = f"{r.f1:.3f}" if r.f1 is not None else "n/a"
    print(f"{r.status}: {r.steps} view(s); Aacc {acc}  F1 {f1}  sim time {sim}  wall time {r.wall_s:.1f} s "
          f"(flight {r.flight_wall_s:.1f} s); photos {r.photos_received} of {r.photos_asked} received; {r.end}")
    if r.status == "completed" and comparison is not None:
        try:
            print(comparison.finish(r, progress=lambda line: print(line, flush=True)))
        except (UavsearchError, KeyboardInterrupt) as e:
            print(f"uavsearch fly: no comparison ({e or 'Ctrl-C'})", file=sys.stderr)
    print(f"flight log: {r.run_dir}  (uavsearch replay {r.run_dir} --out REPLAY_DIR)")
    return 0 if r.status == "completed" else 1


def _check_fly_ports(args) -> None:
    """One line for a port out of range, taken, or meaningless with --connect, naming the flag to change."""
    from .flight.sitl_process import udp_port_in_use

    for flag, port in (("--api-port", args.api_port), ("--gcs-port", args.gcs_port)):
        if not 0 <= port <= 65535:
            raise UavsearchError(f"{flag} {port}: a UDP port is 0-65535")
    if args.api_port and args.connect:
        raise UavsearchError("--api-port is where a vehicle fly starts sends; with --connect the URL names the port")
    if args.api_port and udp_port_in_use(args.api_port):
        raise UavsearchError(f"UDP port {args.api_port} on 127.0.0.1 is in use (another flight or MAVLink client?); "
                             "choose another with --api-port (0, the default: any free port)")


def _speed_arg(text: str):
    if text.lower() == "max":
        return "max"
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"speed must be a number or 'max', got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError("speed must be positive")
    return v


def _add_fly_parser(sub) -> None:
    p = sub.add_parser("fly", help="fly a search mission over MAVLink (starts the simulated vehicle unless --connect)",
                       description="Take off, search with the mission's model (perception, fusion, policy choosing "
                                   "each next view), land; print the found map beside the ground truth.")
    p.add_argument("--mission", default=None, metavar="FILE",
                   help="mission YAML or a name in missions/ (default: wide, the learned wide-area search; "
                        "`--mission default`: the paper's setting 2)")
    p.add_argument("--scene", type=int, default=None, metavar="SEED", help="override the mission's scene seed")
    p.add_argument("--no-compare", action="store_true",
                   help="skip the first view, the best fixed route and the rule on the same scene (teleport) at the end")
    p.add_argument("--speed", type=_speed_arg, default=None, help="1 (real time), N (N x real time) or max")
    p.add_argument("--out", type=Path, default=None, metavar="RUN_DIR", help="flight log directory (default runs/fly__...)")
    p.add_argument("--connect", default=None, metavar="URL",
                   help="fly an already running vehicle instead, e.g. udpin:127.0.0.1:14540")
    p.add_argument("--gcs-port", type=int, default=14550,
                   help="the started vehicle's ground-station link sends here (QGroundControl; 0: off; on a shared "
                        "machine another port or 0, so your ground station sees only your vehicle)")
    p.add_argument("--api-port", type=int, default=0,
                   help="the UDP port this controller listens on, where the started vehicle's API link sends "
                        "(default 0: any free port)")
    p.add_argument("--vehicles", type=int, default=None, metavar="N",
                   help="fly N vehicles on one map (default: the mission's team.vehicles, else 1; a team planner's "
                        "mission, e.g. missions/wide_team.yaml)")
    p.add_argument("--mission-time", type=float, default=None, metavar="S",
                   help="(a scene family's mission) simulated seconds of flight the team searches for")
    p.set_defaults(func=_cmd_fly, exit_at_once=True)


def _add_vehicle_option(p) -> None:
    """`uavsearch eval search --vehicle mavlink`: fly the test scenes instead (mission_controller)."""
    p.add_argument("--vehicle", choices=("teleport", "mavlink"), default="teleport",
                   help="mavlink: fly every test scene over MAVLink and compare with teleport (one setting)")
    p.add_argument("--mission", default=None, metavar="FILE", help="(--vehicle mavlink) mission to fly")
    p.add_argument("--speed", type=_speed_arg, default="max", help="(--vehicle mavlink) speed factor (default max)")
    p.add_argument("--scenes", type=int, nargs="+", default=None, metavar="SEED",
                   help="(--vehicle mavlink) these scene seeds instead of the setting's test scenes")
    teleport = p.get_default("func")

    def run(args):
        if args.vehicle == "teleport":
            return teleport(args)
        from .fly.missions import load_mission  # lazy: torch (2-5 s)
        from .parallel import Executor
        from .fly.flight_vs_teleport import eval_flight_vs_teleport

        setting = 2 if str(args.setting) == "all" else int(args.setting)
        res = eval_flight_vs_teleport(load_mission(args.mission), setting, args.split or "paper", args.speed, args.out,
                                      args.scenes, progress=args.progress, executor=Executor.from_args(args))
        print(res["table"].read_text())
        print(f"wrote {res['table']}")
        return 0

    p.set_defaults(func=run)


def _cmd_replay(args) -> int:
    from .replay.replay import recorded_flight, replay_command  # lazy: torch (2-5 s)

    recorded_flight(args)  # a flag that contradicts the run folder's record: one line, before any output
    if args.html is not None:
        from .replay.flight_review import write_flight_review

        print(f"wrote {write_flight_review(args.log, args.html or None, mission_file=args.mission)}")
        if args.out is None:
            return 0
    if args.out is None:
        raise UavsearchError("replay: give --out DIR (plots, video) and/or --html [FILE] (flight review page)")
    return replay_command(args)


def _add_replay_parser(sub) -> None:
    p = sub.add_parser("replay", help="replay a flight log (run directory) or any MAVLink .tlog into plots and a video")
    p.add_argument("log", type=Path, metavar="RUN_DIR|FILE.tlog", help="a flight log directory, or a telemetry log")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="output folder (PNGs, video, summary)")
    p.add_argument("--html", nargs="?", const="", default=None, metavar="FILE",
                   help="write the flight review page (one self-contained HTML; default RUN_DIR/flight_review.html "
                        "or FILE.tlog's name with .html)")
    p.add_argument("--fusion", default=None, help="re-fuse the logged per-view outputs with another method")
    p.add_argument("--scene", type=int, default=None, metavar="SEED", help="(.tlog) scene to re-render the camera in")
    p.add_argument("--setting", default=None, help="(.tlog) paper setting or scene family of the scene (default 2)")
    p.add_argument("--occupied-cells", type=int, default=None, metavar="K", help="(.tlog) K instead of --setting")
    p.add_argument("--mission", default=None, metavar="FILE",
                   help="(.tlog) mission whose perception / fusion / home to use (default missions/default.yaml)")
    p.add_argument("--every", type=float, default=None, metavar="S",
                   help="(.tlog) also take a view every S seconds of the log (default: at each CAMERA_IMAGE_CAPTURED)")
    p.add_argument("--video", choices=("gif", "mp4"), default="gif", help="video format (default gif)")
    p.set_defaults(func=_cmd_replay)


# --------------------------------------------------------------------------------------------------
# train / eval: groups whose subcommands live with their code


TRAIN_HELP = "train in teleport mode: perception (stage 1), then fusion + policy (stage 2)"
EVAL_HELP = ("evaluate: single-view perception (Table I, Fig. 4), search methods (Table II, Fig. 6), "
             "perception against its targets, teams of vehicles")


def _add_train_parser(sub) -> None:
    # lazy: torch (2-5 s); built only when `train` is the command (build_parser)
    from .search.train.perception import add_train_perception_parser
    from .search.train.policy import add_train_policy_parser
    from .search.train.map_policy import add_train_map_parser
    from .search.train.reactive import add_train_reactive_parser
    from .search.train.fusion import add_train_fusion_parser

    train = sub.add_parser("train", help=TRAIN_HELP)
    tsub = train.add_subparsers(dest="train_cmd", required=True, metavar="{perception,policy,reactive,map,fusion}")
    add_train_perception_parser(tsub)
    add_train_policy_parser(tsub)
    add_train_reactive_parser(tsub)
    add_train_map_parser(tsub)
    add_train_fusion_parser(tsub)


def _add_eval_parser(sub) -> None:
    # lazy: torch (2-5 s); built only when `eval` is the command (build_parser)
    from .search.evaluate.perception import add_eval_perception_parser
    from .search.evaluate.search import add_eval_search_parser
    from .search.evaluate.single_view import add_eval_single_view_parser
    from .search.evaluate.team import add_eval_team_parser

    ev = sub.add_parser("eval", help=EVAL_HELP)
    esub = ev.add_subparsers(dest="eval_cmd", required=True, metavar="{single-view,search,perception,team}")
    add_eval_single_view_parser(esub)
    add_eval_search_parser(esub)
    add_eval_perception_parser(esub)
    add_eval_team_parser(esub)
    _add_vehicle_option(esub.choices["search"])


DATASET_HELP = "labelled datasets out: views with person boxes and instance masks (COCO, YOLO)"


def _add_dataset_parser(sub) -> None:
    # lazy: the scene and render modules (see _scene_from_args); built only when `dataset` is the command
    from .search.data.dataset_export import add_dataset_parser

    add_dataset_parser(sub, DATASET_HELP)


# --------------------------------------------------------------------------------------------------


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole CLI; with `command` given, the torch-heavy train / eval groups are built only when named
    (so `uavsearch --help` or `uavsearch scene ...` does not import torch)."""
    parser = argparse.ArgumentParser(
        prog="uavsearch",
        description="Flight-dynamics-realistic MAVLink UAV testbed for active object search.",
    )
    parser.add_argument("--version", action="version", version=f"uavsearch {__version__}")
    sub = parser.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    _add_scene_parser(sub)
    if command is None or command == "sitl":
        from .flight.sitl import add_sitl_parser  # lazy: the autopilot, pymavlink and numpy cost --help 0.2 s

        add_sitl_parser(sub)
    else:
        sub.add_parser("sitl", help="run the simulated vehicle as a PX4-flavoured MAVLink system")
    for name, add, text in (("train", _add_train_parser, TRAIN_HELP), ("eval", _add_eval_parser, EVAL_HELP),
                            ("dataset", _add_dataset_parser, DATASET_HELP)):
        if command is None or command == name:
            add(sub)
        else:
            sub.add_parser(name, help=text)
    _add_fly_parser(sub)
    _add_replay_parser(sub)
    if command is None or command == "mission":
        from .fly.mission_upload import add_mission_parser  # lazy: .plan parsing and numpy cost --help 0.1 s

        add_mission_parser(sub)
    else:
        sub.add_parser("mission", help="QGroundControl .plan missions: upload (and fly) one")
    return parser


def main(argv: list[str] | None = None) -> int:
    as_program = argv is None
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(command=next((a for a in argv if not a.startswith("-")), ""))
    args = parser.parse_args(argv)
    code = run_command(_check_out_then(args.func), args)
    if as_program:  # a program about to exit: its last garbage collection would walk torch's object graph
        gc.freeze()  # for nothing (0.25-0.3 s CPU after `import torch`, measured)
        if getattr(args, "exit_at_once", False):
            # `fly` has closed its logs and leaves no child to wait for (its vehicle exits on its own): skip
            # the interpreter's teardown of torch (another 0.15 s CPU, 1-3 s wall on a busy 2-core machine)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    return code


# Subcommands whose --out names a file (the others name a folder).
_OUT_IS_FILE = {"scene", "train"}


def _check_out_then(func):
    """Refuse an unwritable --out in one line before the command starts any work."""

    def run(args):
        from .paths import prepare_output

        out = getattr(args, "out", None)
        if out is not None:
            prepare_output(out, "file" if args.cmd in _OUT_IS_FILE else "dir")
        if getattr(args, "html", None):  # replay --html FILE
            prepare_output(args.html, "file")
        return func(args)

    return run


if __name__ == "__main__":
    sys.exit(main())
