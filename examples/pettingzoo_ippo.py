"""Independent PPO with one shared network (IPPO) on uavsearch's PettingZoo team env, in plain torch, then the trained
team against the team planners on the same validation scenes, paired per scene with a 95% bootstrap interval.

    python examples/pettingzoo_ippo.py                            # a few minutes on 2 CPU cores
    python examples/pettingzoo_ippo.py --total-decisions 200000   # longer

The env is `uavsearch.envs.team_parallel_env` (3 vehicles, 80 s of flight, Bayes fusion with prior 0.5: the team
task of missions/wide_team.yaml). Each step one vehicle has arrived and decides; the others can only keep going,
so only the deciding vehicle's transitions train the network: an agent's transition runs from one of its
decisions to its next, which makes each vehicle's episode a semi-Markov chain (a decision's next value is the same
vehicle's at its next decision). Its reward is, by default, the change of the map's F1 that the view it chose made
(``reward="f1"``, ``credit="own"``): with the N_tp - N_fp reward (``--reward shaped``) the team learned to look
where it would see nothing (most views of the wide family add false positives before true ones), and with the
team's reward shared (``--credit team``) a choice's effect drowns in the other vehicles' views.
The network scores every viewpoint from what the observation says about its footprint (the fused map's entropy
and p there, cells not seen yet, cells another vehicle is about to see), its flight time from here and its
altitude, one score per viewpoint by one small MLP, masked by ``action_mask``; a critic reads the same features
pooled. The run writes ``runs/pettingzoo_ippo__<seed>__<time>/``: args.json, metrics.csv, policy.pt, eval.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.envs import team_parallel_env
from uavsearch.paths import RUNS_DIR
from uavsearch.search.agents import PLANNERS
from uavsearch.search.metrics import RESAMPLES, bootstrap_ci
from uavsearch.search.evaluate.team import VARIANTS, team_scores
from uavsearch.search.train.runs import MetricsCsv, seed_everything, start_run
from uavsearch.search.wide_policies import binary_entropy, footprints


@dataclass
class Args:
    vehicles: int = opt(3, "vehicles in the team")
    mission_time_s: float = opt(80.0, "simulated seconds of flight")
    fusion: str = opt("bayes:0.5", "the team's fusion (missions/wide_team.yaml's)")
    reward: str = opt("f1", "the env's reward: f1 (the change of the map's F1 a view made), shaped or terminal")
    credit: str = opt("own", "the env's reward credit: own (each view's to its vehicle) or team (shared)")
    train_scenes: int = opt(20, "train on the first N training scenes of the wide family")
    val_scenes: int = opt(50, "evaluate on the first N validation scenes")
    total_decisions: int = opt(30_000, "vehicle decisions to train on (a few minutes on 2 shared cores)")
    episodes_per_update: int = opt(16, "team episodes per PPO update (each about 20 decisions)")
    learning_rate: float = opt(3e-3, "Adam's, annealed linearly to 0")
    gamma: float = opt(1.0, "discount per decision (the mission time bounds an episode)")
    gae_lambda: float = opt(0.95, "GAE's lambda")
    update_epochs: int = opt(8, "epochs per update")
    minibatch: int = opt(128, "decisions per minibatch")
    clip_coef: float = opt(0.2, "the surrogate's clip")
    ent_coef: float = opt(0.01, "entropy bonus")
    vf_coef: float = opt(0.5, "value loss weight")
    max_grad_norm: float = opt(0.5, "gradient clip")
    hidden: int = opt(64, "hidden units of the scorer and the critic")
    seed: int = opt(1, "seeds random, numpy, torch and the envs")
    bootstrap: int = opt(RESAMPLES, "bootstrap resamples over scenes")
    bootstrap_seed: int = opt(0, "seed of the bootstrap resamples")
    threads: int = opt(1, "torch CPU threads")
    runs_dir: str = opt(str(RUNS_DIR), "parent of the run directory")
    progress: bool = opt(True, "progress bars")


class ViewpointFeatures(nn.Module):
    """(B, P, F) per-viewpoint features and (B, G) global ones from a batch of the team env's observations."""

    def __init__(self, env):
        super().__init__()
        cfg = env.config
        foot = footprints(cfg).float()
        self.register_buffer("foot", foot)  # (P, N)
        self.register_buffer("size", foot.sum(1).clamp(min=1.0))
        self.register_buffer("cost", torch.as_tensor(cfg.lattice.flight_time_s, dtype=torch.float32))
        z = torch.tensor(cfg.lattice.positions_enu[:, 2], dtype=torch.float32)
        self.register_buffer("alt", (z - z.min()) / (z.max() - z.min()).clamp(min=1.0))
        self.T = float(env.mission_time_s)

    def forward(self, o: dict) -> tuple[torch.Tensor, torch.Tensor]:
        B = o["fused"].shape[0]
        fused = o["fused"].reshape(B, -1)
        H = binary_entropy(fused)
        unseen = (o["cell_views"].reshape(B, -1) == 0).float()
        claimed = o["others_to"].sum(1).clamp(max=1.0)  # (B, P) viewpoints the others fly to
        soon = (claimed @ self.foot).clamp(max=1.0)  # (B, N) cells about to be seen
        cost = o["position"] @ self.cost  # (B, P) seconds from here
        left = o["time_left_s"] / self.T  # (B, 1)
        gain = (H * (1.0 - soon)) @ self.foot.T / self.size
        per_s = (H * (1.0 - soon)) @ self.foot.T / cost.clamp(min=1.0) / 10.0
        feats = torch.stack([gain, per_s, H @ self.foot.T / self.size, fused @ self.foot.T / self.size,
                             unseen @ self.foot.T / self.size, soon @ self.foot.T / self.size, cost / self.T,
                             self.alt.expand(B, -1), left.expand(-1, self.foot.shape[0])], -1)
        glob = torch.cat([left, H.mean(1, keepdim=True), unseen.mean(1, keepdim=True), fused.mean(1, keepdim=True),
                          o["others_eta_s"] / self.T], 1)
        return feats, glob


class TeamActorCritic(nn.Module):
    def __init__(self, env, hidden: int):
        super().__init__()
        self.features = ViewpointFeatures(env)
        F, G = 9, 4 + env.V - 1
        self.score = nn.Sequential(nn.Linear(F, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                   nn.Linear(hidden, 1))
        self.stop = nn.Sequential(nn.Linear(G, hidden), nn.Tanh(), nn.Linear(hidden, 1))  # KEEP_GOING (= stop)
        nn.init.constant_(self.stop[-1].bias, -4.0)  # stopping early loses views: rare until learned otherwise
        self.value = nn.Sequential(nn.Linear(2 * F + G, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                   nn.Linear(hidden, 1))

    def forward(self, o: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """(masked logits (B, P + 1), value (B,))."""
        feats, glob = self.features(o)
        mask = o["action_mask"].bool()
        logits = torch.cat([self.score(feats).squeeze(-1), self.stop(glob)], 1)
        logits = logits.masked_fill(~mask, -1e9)
        m = mask[:, :-1, None].float()
        pooled = torch.cat([(feats * m).sum(1) / m.sum(1).clamp(min=1.0), (feats - 1e3 * (1 - m)).amax(1).clamp(min=-1.0),
                            glob], 1)
        return logits, self.value(pooled).squeeze(-1)


def batch_obs(obs: list[dict]) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(np.stack([o[k] for o in obs])).float() for k in obs[0]}


def run_episodes(envs, net, n: int, greedy: bool = False, options=None) -> tuple[list, list]:
    """n team episodes over `envs` stepped together (one forward a step for every env's deciding vehicle):
    (per agent-episode lists of transitions [obs, action, logp, value, reward], final F1 per episode)."""
    chains, finals = [], []
    started = 0
    live = []
    for env in envs[:n]:
        obs, _ = env.reset(options=options[started] if options else None)
        started += 1
        live.append([env, obs, {a: [] for a in env.agents}])
    while live:
        deciders = [e.deciding_agent for e, _, _ in live]
        with torch.no_grad():
            logits, value = net(batch_obs([obs[d] for (_, obs, _), d in zip(live, deciders)]))
            dist = torch.distributions.Categorical(logits=logits)
            act = logits.argmax(1) if greedy else dist.sample()
            logp = dist.log_prob(act)
        nxt = []
        for i, ((env, obs, mine), d) in enumerate(zip(live, deciders)):
            acts = {a: env.KEEP_GOING for a in env.agents}
            acts[d] = int(act[i])
            mine[d].append([{k: v for k, v in obs[d].items()}, int(act[i]), float(logp[i]), float(value[i]), 0.0])
            obs2, rew, term, _, info = env.step(acts)
            for a, r in rew.items():
                if mine[a]:
                    mine[a][-1][4] += r
            if env.agents:
                nxt.append([env, obs2, mine])
            else:
                chains += [c for c in mine.values() if c]
                finals.append(next(iter(info.values()))["f1"])
                if started < n:
                    o, _ = env.reset(options=options[started] if options else None)
                    started += 1
                    nxt.append([env, o, {a: [] for a in env.agents}])
        live = nxt
    return chains, finals


def ppo_update(net, opt, chains, args: Args) -> dict:
    obs, acts, logps, advs, rets = [], [], [], [], []
    for c in chains:  # GAE along each vehicle's own decisions; its last one ends its episode
        v = [t[3] for t in c] + [0.0]
        last = 0.0
        adv = [0.0] * len(c)
        for k in reversed(range(len(c))):
            delta = c[k][4] + args.gamma * v[k + 1] - v[k]
            last = delta + args.gamma * args.gae_lambda * last
            adv[k] = last
        for k, t in enumerate(c):
            obs.append(t[0]), acts.append(t[1]), logps.append(t[2]), advs.append(adv[k]), rets.append(adv[k] + v[k])
    b = batch_obs(obs)
    acts, logps = torch.tensor(acts), torch.tensor(logps)
    advs, rets = torch.tensor(advs, dtype=torch.float32), torch.tensor(rets, dtype=torch.float32)
    n = len(acts)
    stats = {}
    for _ in range(args.update_epochs):
        perm = torch.randperm(n)
        for i in range(0, n, args.minibatch):
            j = perm[i:i + args.minibatch]
            logits, value = net({k: x[j] for k, x in b.items()})
            dist = torch.distributions.Categorical(logits=logits)
            logp = dist.log_prob(acts[j])
            ratio = (logp - logps[j]).exp()
            a = advs[j]
            a = (a - a.mean()) / (a.std() + 1e-8) if len(j) > 1 else a
            pg = torch.max(-a * ratio, -a * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
            v_loss = 0.5 * ((value - rets[j]) ** 2).mean()
            ent = dist.entropy().mean()
            loss = pg - args.ent_coef * ent + args.vf_coef * v_loss
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(net.parameters(), args.max_grad_norm)
            opt.step()
            with torch.no_grad():
                stats = {"losses/policy": float(pg), "losses/value": float(v_loss), "losses/entropy": float(ent),
                         "losses/approx_kl": float(((ratio - 1) - (logp - logps[j])).mean())}
    return {"batch_decisions": n, **stats}


def evaluate(net, args: Args) -> tuple[list[dict], np.ndarray]:
    """The trained team (greedy) and every team planner on the same validation scenes, with the same fusion:
    rows of AF1 and the paired difference (IPPO minus planner) with its bootstrap interval."""
    env = team_parallel_env(vehicles=args.vehicles, mission_time_s=args.mission_time_s, fusion=args.fusion,
                            part="val", limit=args.val_scenes, progress=args.progress)
    seeds = env.scenes.seeds
    _, ours = run_episodes([env], net, len(seeds), greedy=True, options=[{"scene_seed": s} for s in seeds])
    ours = np.asarray(ours)
    rows = [{"team": "IPPO (this run, greedy)", "af1": float(ours.mean()), "diff": None}]
    cache = env.scenes.cache
    specs = [s for k in PLANNERS for s in VARIANTS.get(k, (k,))]
    for spec in tqdm(specs, desc="team planners", disable=not args.progress):
        f1 = team_scores(cache, spec, args.fusion, args.vehicles, args.mission_time_s)["f1"]
        m, lo, hi = bootstrap_ci(ours - f1, args.bootstrap, args.bootstrap_seed)
        rows.append({"team": spec, "af1": float(f1.mean()), "diff": (m, lo, hi)})
    return rows, ours


def train(args: Args) -> dict:
    seed_everything(args.seed)
    run_dir = start_run(args, "pettingzoo_ippo", args.seed)
    kw = dict(vehicles=args.vehicles, mission_time_s=args.mission_time_s, fusion=args.fusion, part="train",
              limit=args.train_scenes, reward=args.reward, credit=args.credit, progress=args.progress)
    envs = [team_parallel_env(**kw) for _ in range(args.episodes_per_update)]
    for i, env in enumerate(envs):
        env.reset(seed=args.seed * 1000 + i)  # each env's scene draws from its own seeded RNG from here on
    net = TeamActorCritic(envs[0], args.hidden)
    opt = torch.optim.Adam(net.parameters(), lr=args.learning_rate, eps=1e-5)
    metrics = MetricsCsv(run_dir / "metrics.csv")
    t0, done = time.perf_counter(), 0
    bar = tqdm(total=args.total_decisions, desc="IPPO", unit="decision", disable=not args.progress)
    while done < args.total_decisions:
        for g in opt.param_groups:
            g["lr"] = args.learning_rate * max(1.0 - done / args.total_decisions, 0.05)
        chains, finals = run_episodes(envs, net, args.episodes_per_update)
        stats = ppo_update(net, opt, chains, args)
        done += stats["batch_decisions"]
        bar.update(stats["batch_decisions"])
        bar.set_postfix(f1=f"{np.mean(finals):.3f}")
        metrics.log({"decisions": done, "charts/final_f1": float(np.mean(finals)),
                     "charts/decisions_per_s": done / (time.perf_counter() - t0), **stats})
    bar.close()
    metrics.close()
    torch.save({"state_dict": net.state_dict(), "args": vars(args)}, run_dir / "policy.pt")
    train_s = time.perf_counter() - t0
    rows, ours = evaluate(net, args)
    lines = [f"# IPPO against the team planners ({args.vehicles} vehicles, {args.mission_time_s:g} s, "
             f"{args.fusion}; {len(ours)} validation scenes of the wide family)", "",
             f"Trained on {args.total_decisions} decisions over the first {args.train_scenes} training scenes in "
             f"{train_s:.0f} s (seed {args.seed}); Δ: per-scene AF1 of IPPO minus the planner's [95% bootstrap "
             f"interval over scenes, {args.bootstrap} resamples, seed {args.bootstrap_seed}].", "",
             "| team | AF1 | Δ IPPO − team |", "|---|---|---|"]
    for r in rows:
        d = "" if r["diff"] is None else f"{r['diff'][0]:+.3f} [{r['diff'][1]:+.3f}, {r['diff'][2]:+.3f}]"
        lines.append(f"| {r['team']} | {r['af1']:.3f} | {d} |")
    (run_dir / "eval.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"\nwrote {run_dir}")
    return {"run_dir": run_dir, "rows": rows, "decisions": done}


def main(argv=None) -> int:
    args = dataclass_from_args(Args, add_dataclass_args(argparse.ArgumentParser(
        description=__doc__.splitlines()[0]), Args).parse_args(argv))
    torch.set_num_threads(args.threads)
    train(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
