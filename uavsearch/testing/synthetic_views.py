"""A synthetic view cache for fast search tests: per-view cell estimates that are better near nadir.

A cell's estimate is correct with a margin that decays with its ground distance from the camera, and
the cell feature carries that distance (plus noise), so a confidence net can learn whom to trust and a
policy can learn where to fly. No rendering, no perception net.
"""

import numpy as np
import torch

from uavsearch.search.config import SearchConfig
from uavsearch.search.data.view_cache import ViewCache


def synthetic_cache(num_scenes: int = 4, k: int = 5, seed: int = 0, cell_dim: int = 6, global_dim: int = 16,
                    config: SearchConfig | None = None) -> ViewCache:
    """`config` (default: the paper's) decides the lattice: one column per viewpoint."""
    rng = np.random.default_rng(seed)
    config = config or SearchConfig()
    dist = config.lattice.cell_distances.numpy()  # (P, N)
    P, N = dist.shape
    occ = np.zeros((num_scenes, N), bool)
    for s in range(num_scenes):
        occ[s, rng.choice(N, k, replace=False)] = True
    quality = np.exp(-dist / 15.0)[None]  # (1, P, N)
    noise = rng.normal(0, 1.0, (num_scenes, P, N))
    logit = np.where(occ[:, None, :], 1.0, -1.0) * (4.0 * quality - 0.8) + noise - 1.0
    p1 = 1.0 / (1.0 + np.exp(-logit))
    log_probs = np.log(np.stack([1 - p1, p1], -1).clip(1e-6, 1))
    feats = np.concatenate([quality.repeat(num_scenes, 0)[..., None],
                            rng.normal(0, 0.1, (num_scenes, P, N, cell_dim - 1))], -1)
    glob = rng.normal(0, 1, (num_scenes, P, global_dim))
    return ViewCache(
        scene_seed=np.arange(num_scenes, dtype=np.int64), occupied_cells=np.full(num_scenes, k, np.int64),
        occupancy=torch.as_tensor(occ), log_probs=torch.as_tensor(log_probs, dtype=torch.float32),
        cell_features=torch.as_tensor(feats, dtype=torch.float32),
        global_feature=torch.as_tensor(glob, dtype=torch.float32).relu(),
        cell_area_px=torch.full((num_scenes, P, N), 192.0), valid=torch.ones(num_scenes, P, N, dtype=torch.bool),
        perception_tag="synthetic", config=config,
    )


def synthetic_wide_cache(num_scenes: int = 4, seed: int = 0, config: SearchConfig | None = None,
                         k: int = 10, cell_dim: int = 6) -> ViewCache:
    """A synthetic cache on a wide lattice (default: the wide family's) where each view measures only its
    footprint, with K people's pixels in the occupied cells it sees (`cell_dim` features per cell: a fusion that
    reads the shipped perception's features needs its 104)."""
    from uavsearch.search.config import setting_config
    from uavsearch.search.wide_policies import footprints

    config = config or setting_config("wide")
    c = synthetic_cache(num_scenes, k=k, seed=seed, config=config, cell_dim=cell_dim)
    valid = footprints(config)[None].expand(num_scenes, -1, -1).clone()
    return c._replace(valid=valid, person_px=(c.occupancy[:, None, :] & valid).int() * 5)
