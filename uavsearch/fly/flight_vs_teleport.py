"""Flight versus teleport on the test scenes (`uavsearch eval search --vehicle mavlink`): the same mission
flown over MAVLink and run with the teleport vehicle, scene by scene, and the table comparing them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..parallel import Executor, map_scenes
from ..paths import RUNS_DIR
from ..search.metrics import map_accuracy, map_f1
from ..search.views import TeleportVehicle
from ..world.settings import scene_seeds
from .mission_controller import fly

if TYPE_CHECKING:
    from ..search.agents import LoadedAgent


def teleport_episode(mission, loaded: LoadedAgent | None = None):
    """The same mission's search with the teleport vehicle (exact poses, no dynamics): (fused map, positions)."""
    import torch

    from ..search.search_loop import LiveViews, run_search

    config = mission.search_config()
    loaded = loaded or mission.agent(config)
    spec = mission.scene_spec()
    labels = np.asarray(spec.occupancy_array(), dtype=bool)
    gen = torch.Generator().manual_seed(int(mission.policy_seed))
    with TeleportVehicle(spec, config) as v, torch.no_grad():
        ep = run_search(LiveViews(v, loaded.perception, labels), loaded.agent, config.budget_T, generator=gen)
    pos = config.lattice.positions_enu[ep.lattice_idx[0].numpy()]
    return ep.maps[0, -1].numpy(), pos, labels


def flight_vs_teleport_scene(job) -> dict:
    """The per-scene task: fly (mission, scene seed) and run the same episode teleported; one table row.
    The flight log goes to <out>/flight_scene<seed> on the machine that flew it."""
    mission, seed, out = job
    r = fly(mission, out=Path(out) / f"flight_scene{seed}", progress=lambda s: None, gcs_port=0)
    fused_t, pos_t, labels = teleport_episode(mission)
    return dict(scene=seed, status=r.status.split(":")[0], flight_acc=r.acc, flight_f1=r.f1,
                teleport_acc=float(map_accuracy(fused_t, labels)), teleport_f1=float(map_f1(fused_t, labels)),
                same_route=bool(len(r.positions) == len(pos_t) and np.allclose(np.asarray(r.positions), pos_t)),
                wall_s=r.wall_s, flight_wall_s=r.flight_wall_s, sim_s=r.sim_time_s)


def eval_flight_vs_teleport(mission, setting: int = 2, split: str = "paper", speed="max", out=None,
                            scenes: list[int] | None = None, progress: bool = True,
                            executor: Executor | None = None) -> dict:
    """Fly the mission on every test scene of a setting and run the same episode in teleport mode.

    The policy acts greedily (its most likely move) in both modes, so the two runs take the same route
    unless a view's outputs differ enough to change a decision; what separates them is then the flown
    vehicle's pose error (projection at the reported pose) and the render at the true, not the nominal, pose.
    `mission` (a missions.Mission) gives everything but the scene. Each scene is one task
    (flight_vs_teleport_scene) on `executor` (default: one at a time, here).
    """
    base = mission.with_overrides(**{"scene.setting": setting, "scene.occupied_cells": None,
                                                         "greedy_policy": True, "flight.speed": speed})
    seeds = scenes or scene_seeds(setting, split, "test")
    out = Path(out or RUNS_DIR / f"eval_flight_s{setting}")
    out.mkdir(parents=True, exist_ok=True)

    def record(_, row):
        with open(out / "flight_vs_teleport.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")

    jobs = [(base.with_overrides(**{"scene.seed": seed}), int(seed), str(out.resolve())) for seed in seeds]
    rows = map_scenes(flight_vs_teleport_scene, jobs, executor or Executor("local", 1),
                      desc=f"flight vs teleport, setting {setting}", progress=progress, on_result=record)
    ok = [r for r in rows if r["flight_acc"] is not None]
    mean = lambda k: float(np.mean([r[k] for r in ok])) if ok else float("nan")  # noqa: E731
    summary = dict(setting=setting, split=split, scenes=len(rows), completed=len(ok),
                   flight_Aacc=mean("flight_acc"), flight_AF1=mean("flight_f1"), teleport_Aacc=mean("teleport_acc"),
                   teleport_AF1=mean("teleport_f1"), same_route=sum(r["same_route"] for r in ok),
                   wall_s_per_mission=mean("wall_s"), flight_wall_s_per_mission=mean("flight_wall_s"),
                   sim_s_per_mission=mean("sim_s"), speed=speed)
    lines = [f"# Flight vs. teleport, setting {setting} ({split} split, {len(ok)}/{len(rows)} test scenes flown, "
             f"speed {speed}, {base.fusion} fusion + {base.policy} policy"
             f"{' acting greedily' if base.policy == 'learned' else ''})", "",
             "| mode | Aacc (%) | AF1 |", "|---|---|---|",
             f"| teleport | {100 * summary['teleport_Aacc']:.3f} | {summary['teleport_AF1']:.3f} |",
             f"| flight (MAVLink) | {100 * summary['flight_Aacc']:.3f} | {summary['flight_AF1']:.3f} |",
             f"| difference | {100 * (summary['flight_Aacc'] - summary['teleport_Aacc']):+.3f} | "
             f"{summary['flight_AF1'] - summary['teleport_AF1']:+.3f} |", "",
             f"Same route in both modes: {summary['same_route']}/{len(ok)} scenes. Wall time per flown mission: "
             f"{summary['wall_s_per_mission']:.1f} s (flight {summary['flight_wall_s_per_mission']:.1f} s, "
             f"{summary['sim_s_per_mission']:.1f} s simulated).", "",
             "| scene | flight acc | flight F1 | teleport acc | teleport F1 | same route | wall s |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        fa = f"{r['flight_acc']:.2f}" if r["flight_acc"] is not None else r["status"]
        ff = f"{r['flight_f1']:.3f}" if r["flight_f1"] is not None else ""
        lines.append(f"| {r['scene']} | {fa} | {ff} | {r['teleport_acc']:.2f} | {r['teleport_f1']:.3f} | "
                     f"{'yes' if r['same_route'] else 'no'} | {r['wall_s']:.1f} |")
    (out / "flight_vs_teleport.md").write_text("\n".join(lines) + "\n")
    (out / "flight_vs_teleport.json").write_text(json.dumps({"summary": summary, "rows": rows}, indent=2) + "\n")
    return {"summary": summary, "rows": rows, "table": out / "flight_vs_teleport.md"}
