"""What the flown scene gives other searches: the first view alone, the best fixed route and the hand-written rule,
on the same scene, budget, perception and fusion as the flight, beside the flight's own result.

A flight's F1 means little on its own: a scene may be easy or hard. The comparison runs in teleport mode (the
camera set at each viewpoint and rendered there: no dynamics, so no pose error and the lattice's flight times),
with the evaluation's own loops (run_search, run_team) over one TeleportVehicle, whose renders the rows share,
and the evaluation's methods:

- a single vehicle on a scene family: Table III's best fixed route and the rule's variant, as the committed table
  of the family names them for the budget (chosen there on validation scenes), with the flight's fusion;
- the paper's settings: Table II's fixed-route reference (the coverage route) and its hand-written policy
  (greedy uncertainty);
- a team: the fixed partition and the rule for a team (search/team.py's planners);

and the flight's own method teleported on the scene too, which separates what flying changed from what the
method chose. `uavsearch fly` prints the table and writes it to the run folder (comparison.json).
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from pathlib import Path

import numpy as np

from ..flight.camera import SCENE_FILE
from ..logs.flight_log import read_flight_log
from ..errors import UavsearchError
from ..paths import display_path
from ..world.scene import load_scene

COMPARISON_FILE = "comparison.json"
FIRST_VIEW = "first_view"
OWN = "teleport_own"
FLOWN = "flown"
# Table III's hand-made fixed routes (the registry builds them); its view sets are searched on training scenes
HAND_MADE = ("lawnmower_high", "lawnmower_low", "survey_inner", "survey_outer")
COMPARING = ("comparing: the same scene searched by the first view alone, the best fixed route and the rule "
             "(teleport: rendered at each viewpoint) ...")
OWN_NAMES = {"map": "learned wide-area policy", "learned": "learned policy (paper)", "reactive": "reactive policy"}


class _SceneViews:
    """The rows' view source: a LiveViews episode on the shared teleport vehicle whose perception outputs are kept
    per viewpoint, as a view cache keeps them (each viewpoint rendered and perceived once for every row)."""

    def __init__(self, vehicle, perception, labels, seen: dict):
        from ..search.search_loop import LiveViews

        self.live, self.seen = LiveViews(vehicle, perception, labels), seen
        self.config, self.batch_size, self.device, self.labels = (self.live.config, 1, self.live.device,
                                                                  self.live.labels)

    def observe(self, lattice_idx):
        i = int(lattice_idx.reshape(-1)[0])
        if i not in self.seen:
            self.seen[i] = self.live.observe(lattice_idx)
        return self.seen[i]


def table3_choice(family: str, budget: str) -> dict:
    """Table III's best fixed route and rule variant for a family and budget ("240 s", "T = 8 views"), from the
    committed table (search/table3_choices.py); a view set searched on training scenes gives way to the best
    hand-made route by the table's validation AF1, which needs no training views."""
    from ..search.table3_choices import table3_choice as read_choice
    from ..search.wide_policies import RULE_VARIANTS

    choice = {"best_fixed": "survey_outer", "rule_variant": None, "source": None, "note": ""}
    try:
        table = read_choice(family, budget)
    except UavsearchError:
        choice["note"] = f"no Table III of {family} in results/: the hand-made defaults"
        return choice
    choice["source"], best = table.source, table.best_fixed
    if best not in HAND_MADE:
        choice["note"] = (f"Table III's best fixed route ({best}) is a view set searched on training scenes; the best "
                          "hand-made one on its validation scenes is shown")
        val = table.val_af1
        best = max(HAND_MADE, key=lambda k: (val.get(k, -1.0), -HAND_MADE.index(k))) if val else choice["best_fixed"]
    choice["best_fixed"] = best
    choice["rule_variant"] = table.rule if table.rule in RULE_VARIANTS else None
    return choice


def _budget_name(config) -> str:
    return f"T = {config.budget_T} views" if config.budget_s is None else f"{config.budget_s:g} s"


def _single_config(mission, config):
    """The one-vehicle search of a family's mission as Table III runs it: the view budget alone, or the time budget
    with as many views as fit (the mission's flight holds both; team_method loads the policy the same way)."""
    views = mission.team.max_views if mission.team is not None else None
    return dataclasses.replace(config, budget_s=None) if views else \
        dataclasses.replace(config, budget_T=config.lattice.num_positions)


def _search_row(key, method, source, agent, config, budget_T=None, seed=0, detail="") -> dict:
    """One teleport episode of `agent` with run_search (the evaluation's loop), scored like Table II / III."""
    import torch

    from ..search.evaluate.wide import flight_seconds
    from ..search.scoring import score_episode
    from ..search.search_loop import run_search

    ep = run_search(source, agent, budget_T, generator=torch.Generator().manual_seed(int(seed)))
    sc = score_episode(ep)
    taken = ep.taken[0] if ep.taken is not None else torch.ones(ep.maps.shape[1], dtype=torch.bool)
    flight = float(ep.flight_s[0]) if ep.flight_s is not None else float(flight_seconds(config, ep.lattice_idx)[0])
    return dict(key=key, method=method, detail=detail, mode="teleport", views=int(taken.sum()), flight_s=flight,
                acc=float(sc.acc[0, -1]), f1=float(sc.f1[0, -1]), route=ep.lattice_idx[0][taken].tolist())


def _team_row(key, method, source, fusion, planner, vehicles, budget_s, max_views=None, seed=0, detail="") -> dict:
    """One teleport episode of a team planner with run_team (the team evaluation's loop)."""
    import torch

    from ..search.metrics import map_accuracy, map_f1
    from ..search.team import run_team

    ep = run_team(source, fusion, planner, vehicles, budget_s, max_views=max_views,
                  generator=torch.Generator().manual_seed(int(seed)))
    final, labels = ep.map_at(budget_s).numpy(), source.labels.numpy()
    taken = ep.taken[0]
    return dict(key=key, method=method, detail=detail, mode="teleport", views=int(taken.sum()),
                flight_s=float(ep.time_s[0][taken].max()) if bool(taken.any()) else 0.0,
                acc=float(map_accuracy(final, labels)[0]), f1=float(map_f1(final, labels)[0]),
                route=ep.lattice_idx[0][taken].tolist())


def _flown_row(mission, result, method: str) -> dict:
    steps = read_flight_log(result.run_dir).steps
    times = [s.sim_time_s for s in steps if s.sim_time_s is not None]
    return dict(key=FLOWN, method=f"this flight: {method}", detail="", mode="flown", views=result.steps,
                flight_s=float(times[-1] - times[0]) if times else float("nan"), acc=result.acc, f1=result.f1,
                route=[s.lattice_idx for s in steps])


def compare(mission, result, progress=None) -> dict:
    """The comparison of a completed flight (a MissionResult of `mission`): its rows and what they were run with."""
    scene_file = Path(result.run_dir) / SCENE_FILE
    spec = load_scene(scene_file) if scene_file.is_file() else mission.scene_spec()
    if progress is not None:
        progress(COMPARING)
    return with_flight(teleport_rows(mission, spec, result.labels), mission, result)


def teleport_rows(mission, spec, labels) -> dict:
    """The comparison's teleport rows on the scene `spec` (ground truth `labels`): everything but the flight's own
    row, so it can run while the vehicle flies (SceneComparison)."""
    import torch

    from ..search.agents import PLANNERS, POLICIES, make_planner
    from ..search.evaluate.wide import LABELS, rule_agent
    from ..search.fusion import fusion_name
    from ..search.perception import load_perception
    from ..search.search_loop import Agent
    from ..search.views import TeleportVehicle

    t0 = time.monotonic()
    mission = mission.check_registry()
    config = mission.search_config()
    labels = np.asarray(labels, dtype=bool)
    own = _own_name(mission)
    out = {"scene": int(spec.seed), "family": mission.family, "vehicles": mission.vehicles, "rows": []}
    rows, seen = out["rows"], {}
    with torch.no_grad(), TeleportVehicle(spec, config) as vehicle:
        if mission.family is None:  # the paper's settings: Table II's rows
            loaded = mission.agent(config)
            fusion, net = loaded.agent.fusion, loaded.perception
            src = lambda: _SceneViews(vehicle, net, labels, seen)  # noqa: E731  (a source is one episode)
            rows.append(_search_row(FIRST_VIEW, "first view alone", src(), loaded.agent, config, 1))
            rows.append(_search_row("coverage", "fixed route", src(), Agent(fusion, POLICIES["coverage"].build(config)),
                                    config, detail="the coverage route (Table II's fixed route)"))
            rows.append(_search_row("greedy", "hand-written rule", src(), Agent(fusion, POLICIES["greedy"].build(config)),
                                    config, detail="greedy uncertainty: toward the most uncertain cells"))
            rows.append(_search_row(OWN, f"{own}, teleported", src(), loaded.agent, config, seed=mission.policy_seed))
            out.update(budget=f"T = {config.budget_T} views", fusion=mission.fusion)
        else:
            method = mission.team_method(config)
            fusion, budget_s, n = method.fusion, float(config.budget_s), mission.vehicles
            net = load_perception(mission.perception_path)[0].for_grid(config.grid.num_cells)
            max_views = mission.team.max_views if mission.team is not None else None
            src = lambda: _SceneViews(vehicle, net, labels, seen)  # noqa: E731
            if n == 1:  # Table III's rows
                single = _single_config(mission, config)
                choice = table3_choice(mission.family, _budget_name(single))
                variant = choice["rule_variant"]
                rule = Agent(fusion, POLICIES["descend_rule"].build(single)) if variant is None else \
                    rule_agent(fusion, single, variant)
                fixed = Agent(fusion, POLICIES[choice["best_fixed"]].build(single))
                rows.append(_search_row(FIRST_VIEW, "first view alone", src(), fixed, single, 1))
                rows.append(_search_row(choice["best_fixed"], "best fixed route", src(), fixed, single,
                                        detail=LABELS[choice["best_fixed"]]))
                rows.append(_search_row("descend_rule", "the rule", src(), rule, single,
                                        detail=f"{LABELS['descend_rule'].removeprefix('the rule: ')} ({variant or 'its default variant'})"))
                out["choices"] = choice
            else:  # a team's: the fixed partition and the rule for a team
                rows.append(_team_row(FIRST_VIEW, "first view alone", src(), fusion, make_planner("partition", config),
                                      n, budget_s, 1))
                for key, name in (("partition", "fixed route"), ("rule", "the rule for a team")):
                    rows.append(_team_row(key, name, src(), fusion, make_planner(key, config), n, budget_s, max_views,
                                          detail=PLANNERS[key].description))
            rows.append(_team_row(OWN, f"{own}, teleported", src(), fusion, method.planner, n, budget_s, max_views))
            out.update(budget=f"{budget_s:g} s of flight" + (f", at most {max_views} views" if max_views else ""),
                       fusion=fusion_name(fusion))
    out.update(perception=display_path(mission.perception_path), wall_s=time.monotonic() - t0)
    return out


def _own_name(mission) -> str:
    return OWN_NAMES.get(mission.policy, f"{mission.policy} {'policy' if mission.family is None else 'planner'}")


def with_flight(teleport: dict, mission, result) -> dict:
    """The teleport rows of the flown scene and, last, the flight's own row."""
    return {**teleport, "rows": [*teleport["rows"], _flown_row(mission, result, _own_name(mission))]}


class SceneComparison:
    """The comparison computed while the vehicle flies: `start(spec, labels)` (fly's `on_scene`, once the vehicle
    has generated the scene) runs the teleport rows in a background thread, so their render process starts and
    their searches run beside the flight instead of after the landing; `finish(result)` adds the flight's row.

    The flight is unchanged by it: the vehicle runs in lockstep with the controller, so a busier controller only
    makes the flight's wall time longer, never its simulated path, and every row draws from its own generator."""

    def __init__(self, mission):
        from ..world.render import start_idle_worker

        self.mission, self._thread, self._rows, self._error = mission, None, None, None
        start_idle_worker(background=True)  # the rows' renderer: its start-up uses the cores the start leaves idle

    def start(self, spec, labels) -> None:
        def run():
            try:
                self._rows = teleport_rows(self.mission, spec, labels)
            except BaseException as e:  # noqa: BLE001 - said by finish(), in the command's own words
                self._error = e

        self._thread = threading.Thread(target=run, name="scene-comparison", daemon=True)
        self._thread.start()

    def finish(self, result, progress=None) -> str:
        """Wait for the rows (saying so if they are not done), write comparison.json, return the table's text."""
        from ..world.render import foreground_workers

        foreground_workers()  # the flight is over: the rows' renderer is no longer background work
        if self._thread is None:  # no scene was handed over (e.g. a vehicle someone else started): compute it now
            return compare_flight(self.mission, result, progress)
        if self._thread.is_alive() and progress is not None:
            progress(COMPARING)
        self._thread.join()
        if self._error is not None:
            raise self._error
        return _write(with_flight(self._rows, self.mission, result), result)


def format_comparison(c: dict) -> str:
    """The comparison as a short text table, then what its fixed route and rule are."""
    scene = f"{c['family']} scene {c['scene']}" if c["family"] else f"scene {c['scene']}"
    team = f"{c['vehicles']} vehicles, " if c["vehicles"] > 1 else ""
    lines = [f"The same {scene}, {team}{c['budget']}, {c['fusion']} fusion, searched otherwise (teleport: each view "
             f"rendered at its viewpoint, no flight; {c['wall_s']:.1f} s):"]
    width = max(len(r["method"]) for r in c["rows"])
    lines.append(f"  {'method':<{width}}  {'mode':<8}  views  flight (s)  F1 final")
    for r in c["rows"]:
        f1 = "n/a" if r["f1"] is None else f"{r['f1']:.3f}"
        lines.append(f"  {r['method']:<{width}}  {r['mode']:<8}  {r['views']:>5}  {r['flight_s']:>10.0f}  {f1:>8}")
    lines += [f"  {r['method']}: {r['detail']}" for r in c["rows"] if r.get("detail")]
    choice = c.get("choices") or {}
    if choice.get("source"):
        lines.append(f"  (the fixed route and the rule's variant as {choice['source']} chose them on validation scenes)")
    if choice.get("note"):
        lines.append(f"  ({choice['note']})")
    return "\n".join(lines)


def compare_flight(mission, result, progress=print) -> str:
    """Compare a completed flight, write comparison.json into its run folder, and return the table's text."""
    return _write(compare(mission, result, progress), result)


def _write(c: dict, result) -> str:
    (Path(result.run_dir) / COMPARISON_FILE).write_text(json.dumps(c, indent=1) + "\n")
    return format_comparison(c)


__all__ = ["COMPARISON_FILE", "SceneComparison", "compare", "compare_flight", "format_comparison", "table3_choice",
           "teleport_rows", "with_flight"]
