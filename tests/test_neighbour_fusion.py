"""The neighbour fusion: view by view equals the whole history, saves and loads to the same maps, a spec names it,
and what it cannot do is a one-line error (small synthetic views, no caches)."""

import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.search.agents import make_fusion
from uavsearch.search.fusion import FUSIONS, CalibratedFusion, FusionViews
from uavsearch.search.neighbour_fusion import (CorrectionNet, NeighbourFusion, load_neighbour, save_neighbour,
                                               view_planes)

B, T, N, P, n = 3, 4, 36, 10, 6


def views():
    g = torch.Generator().manual_seed(0)
    p = torch.rand(B, T, N, generator=g)
    valid = torch.rand(B, T, N, generator=g) < 0.7
    area = torch.rand(B, T, N, generator=g) * 400 + 20
    idx = torch.randint(P, (B, T), generator=g)
    return FusionViews(p, valid, area, viewpoints=idx)


def fusion():
    torch.manual_seed(0)
    lowest = torch.arange(P) >= 6
    return NeighbourFusion(CalibratedFusion((1.1, -0.05, -0.3, 0.02), 0.08, 0.25), CorrectionNet(kernel=5).eval(),
                           0.75, lowest, n)


def test_registered_and_view_by_view_equals_the_history():
    f, v = fusion(), views()
    assert FUSIONS["neighbour"] is NeighbourFusion
    whole = f.fuse(v)
    assert torch.allclose(f.prefixes(v)[:, -1], whole, atol=1e-6)
    # the probe's correction, written out: the net over the calibrated map's planes, shifted
    fused = f.base.fuse(v)
    planes = view_planes(fused, v.p, v.valid, v.area_px, v.viewpoints, f.base.coef, f.lowest, n)
    with torch.no_grad():
        want = torch.sigmoid(f.net(planes).flatten(1) + 0.75)
    assert torch.allclose(whole, want, atol=1e-6)


def test_save_load_round_trip_and_spec(tmp_path):
    f, v = fusion(), views()
    path = save_neighbour(f, tmp_path / "nf.pt", {"seed": 0})
    g = load_neighbour(path)
    assert torch.equal(g.fuse(v), f.fuse(v))
    assert torch.equal(make_fusion(f"neighbour:{path}").fuse(v), f.fuse(v))


def test_errors(tmp_path):
    with pytest.raises(UavsearchError, match="not found"):
        make_fusion(f"neighbour:{tmp_path / 'missing.pt'}")
    with pytest.raises(UavsearchError, match="neighbour:PATH"):
        make_fusion("neighbour")
    bad = tmp_path / "bad.pt"
    torch.save({"format": "other"}, bad)
    with pytest.raises(UavsearchError, match="not a neighbour fusion"):
        load_neighbour(bad)
    v = views()
    with pytest.raises(UavsearchError, match="buffered"):
        fusion().fuse_host(v)
    with pytest.raises(UavsearchError, match="viewpoint"):
        fusion().fuse(v._replace(viewpoints=None))
