"""Per-view cell features of a view cache, one memory-mapped float16 file per scene.

A scene family's features are too big to hold whole: the wide family's 73 viewpoints x 900 cells x 104
features are 13.7 MB a scene in float16, 1.37 GB per 100 scenes, 6.8 GB for its 500 training scenes. So
view_cache.build_view_cache writes them here, scene by scene, beside the part's .npz (which then keeps an
empty feature axis), and a reader maps the files and copies only the views it asks for; the page cache,
not the process, holds what was read, and gives it back under memory pressure. A store is a folder
(local, or an fsspec URL: a remote scene is copied once to a local folder to be mapped):

    <dir>/manifest.json   format, perception tag, (P, N, D) and dtype of every scene's features, and
                          "scenes": per finished scene the manifest entries of its two files
    <dir>/<seed>.npy      (P, N, D) float16: row p is the view at lattice position p
    <dir>/<seed>.npz      the scene's other perception outputs (parallel.npz_bytes), so a resumed build
                          skips the scene's perception altogether

A scene is written whole (both files, then its manifest entry), so a killed build resumes at the first
scene it had not finished.
"""

from __future__ import annotations

import io
import tempfile
from pathlib import Path

import numpy as np
import torch

from uavsearch.errors import UavsearchError
from uavsearch.parallel import Store, finished, manifest_entry, npz_bytes

FORMAT = "uavsearch-feature-store/1"
DTYPE = np.float16


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


class FeatureStore:
    """The per-scene feature files of one view-cache part (picklable: the mapped files are not pickled)."""

    def __init__(self, url, perception_tag: str | None = None):
        """Open the store at `url` (a folder or an fsspec URL). `perception_tag` (a writer's) must match the
        tag of what the store holds: a store of other weights is refused, never mixed."""
        self.store = Store(url)
        self.manifest = self.store.read_json("manifest.json")
        if self.manifest is not None and self.manifest.get("format") != FORMAT:
            raise UavsearchError(f"{self.store.url} is not a uavsearch feature store "
                                 f"(format {self.manifest.get('format')!r}); delete it")
        if perception_tag is not None:
            if self.manifest is None:
                self.manifest = {"format": FORMAT, "perception_tag": perception_tag, "shape": None,
                                 "dtype": np.dtype(DTYPE).name, "scenes": {}}
            elif self.manifest["perception_tag"] != perception_tag:
                raise UavsearchError(f"{self.store.url} holds the features of perception "
                                     f"{self.manifest['perception_tag']}, not {perception_tag}; delete it")
        elif self.manifest is None:
            raise UavsearchError(f"{self.store.url} is not a feature store (no manifest.json)")
        self._maps: dict[int, np.ndarray] = {}
        self._local_dir: Path | None = None

    def __reduce__(self):
        return FeatureStore, (self.store.url,)

    def __repr__(self) -> str:
        return f"FeatureStore({self.store.url!r}, {len(self)} scenes)"

    def __len__(self) -> int:
        return len(self.manifest["scenes"])

    @property
    def tag(self) -> str:
        return self.manifest["perception_tag"]

    @property
    def shape(self) -> tuple[int, int, int] | None:
        """(P, N, D) of every scene's features (None while the store is empty)."""
        s = self.manifest["shape"]
        return None if s is None else tuple(s)

    # -- writing (view_cache.build_view_cache, one scene at a time) --

    def done(self, seed: int) -> bool:
        """The scene's two files are written whole (a resumed build skips it)."""
        entry = self.manifest["scenes"].get(str(int(seed)))
        return entry is not None and all(finished(self.store, entry[k], self.tag) for k in ("features", "outputs"))

    def write(self, seed: int, features: np.ndarray, outputs: dict[str, np.ndarray]) -> None:
        """Store one scene: its (P, N, D) features as float16, its other outputs as an .npz; the manifest
        entry last."""
        features = np.asarray(features).astype(DTYPE, copy=False)
        if self.shape is not None and features.shape != self.shape:
            raise UavsearchError(f"{self.store.url}: scene {seed} has features {features.shape}, the store {self.shape}")
        entry = {}
        for name, key, data in (("features", f"{int(seed)}.npy", npy_bytes(features)),
                                ("outputs", f"{int(seed)}.npz", npz_bytes(outputs, compress=False))):
            self.store.write_bytes(key, data)
            entry[name] = manifest_entry(key, data, self.tag)
        self.manifest["shape"] = list(features.shape)
        self.manifest["scenes"][str(int(seed))] = entry
        self.manifest["scenes"] = dict(sorted(self.manifest["scenes"].items(), key=lambda kv: int(kv[0])))
        self.store.write_json("manifest.json", self.manifest)
        self._maps.pop(int(seed), None)

    def outputs(self, seed: int) -> dict[str, np.ndarray]:
        """The scene's other perception outputs, as write() got them."""
        with np.load(io.BytesIO(self.store.read_bytes(f"{int(seed)}.npz"))) as z:
            return {k: z[k] for k in z.files}

    # -- reading --

    def scene(self, seed: int) -> np.ndarray:
        """The scene's (P, N, D) float16 features, memory-mapped (nothing is read until indexed)."""
        seed = int(seed)
        if seed not in self._maps:
            if str(seed) not in self.manifest["scenes"]:
                raise UavsearchError(f"{self.store.url} holds no features of scene {seed}")
            self._maps[seed] = np.load(self._local_file(f"{seed}.npy"), mmap_mode="r")
        return self._maps[seed]

    def _local_file(self, key: str) -> str:
        if self.store.local:
            return self.store.path(key)
        if self._local_dir is None:
            self._local_dir = Path(tempfile.mkdtemp(prefix="uavsearch-features-"))
        path = self._local_dir / key
        if not path.exists():
            path.write_bytes(self.store.read_bytes(key))
        return str(path)

    def read(self, seed: int, views, device="cpu", dtype: torch.dtype | None = None) -> torch.Tensor:
        """(V, N, D) features of one scene's views (lattice indices `views`), read from the mapped file only;
        float16 unless `dtype`."""
        rows = np.asarray(torch.as_tensor(views).cpu(), dtype=np.int64).reshape(-1)
        out = torch.from_numpy(np.ascontiguousarray(self.scene(seed)[rows]))
        return out.to(device=device, dtype=dtype or out.dtype)

    def gather(self, seeds, views, device="cpu", dtype: torch.dtype | None = None) -> torch.Tensor:
        """(B, N, D) features of the views (seeds[b], views[b]), B pairs over any scenes (a batch of episodes);
        each scene's file is read once for all of its views."""
        seeds = np.asarray(seeds, dtype=np.int64).reshape(-1)
        views = np.asarray(torch.as_tensor(views).cpu(), dtype=np.int64).reshape(-1)
        if len(seeds) != len(views):
            raise UavsearchError(f"{len(seeds)} scenes for {len(views)} views")
        P, N, D = self.shape if self.shape is not None else (0, 0, 0)
        out = np.empty((len(seeds), N, D), DTYPE)
        for s in np.unique(seeds):
            at = np.flatnonzero(seeds == s)
            out[at] = self.scene(s)[views[at]]
        t = torch.from_numpy(out)
        return t.to(device=device, dtype=dtype or t.dtype)

    def load(self, seeds) -> torch.Tensor:
        """(S, P, N, D) features of whole scenes, in memory (what a cache loaded with its features holds)."""
        return torch.from_numpy(np.stack([np.asarray(self.scene(s)) for s in seeds]))


__all__ = ["DTYPE", "FORMAT", "FeatureStore"]
