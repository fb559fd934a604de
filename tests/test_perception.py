"""Per-cell perception: the pooled op against the literal masked version, shapes, locality, checkpoints."""

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.geometry import CameraIntrinsics, Grid, cell_label_image, nadir_camera_pose
from uavsearch.search.perception import (
    EMBED_DIM,
    ConfidenceNet,
    ImageEmbedding,
    PerceptionConfig,
    PerceptionNet,
    cell_pooling,
    load_perception,
    pool_cells,
    pool_cells_literal,
    save_perception,
)

INTR = CameraIntrinsics(224, 224, 60.0)
GRID = Grid(10, 5.0)


def _labels(*xy):
    return torch.as_tensor(np.stack([cell_label_image(GRID, INTR, nadir_camera_pose([x, y, 70.0])) for x, y in xy]))


def test_pooling_op_equals_literal_per_cell_masked_pooling():
    torch.manual_seed(0)
    lab = _labels((0.0, 0.0), (20.0, -10.0))
    fmap = torch.rand(2, 8, 56, 56)
    pooling = cell_pooling(lab, 4)
    fast = pool_cells(fmap, pooling)
    slow = pool_cells_literal(fmap, lab, 4)
    assert torch.allclose(fast, slow, atol=1e-5)
    # Pixel counts are exact: they equal the mask sizes.
    for b in range(2):
        counts = torch.bincount((lab[b][lab[b] >= 0]).long().reshape(-1), minlength=100).float()
        assert torch.equal(pooling.pixels[b], counts)


def test_cells_out_of_view_get_zero_pixels_and_zero_features():
    lab = _labels((40.0, 40.0))  # far north-east (off the lattice): the south-west cells are out of view
    pooling = cell_pooling(lab, 4)
    unseen = pooling.pixels[0] == 0
    assert unseen[90]  # SW corner cell (row 9, col 0)
    assert not unseen[9]  # NE corner cell is under the camera
    f = pool_cells(torch.rand(1, 4, 56, 56), pooling)
    assert (f[0, unseen] == 0).all()


def test_pooled_forward_equals_literal_masked_forward_for_a_pointwise_backbone():
    # With 1x1 convolutions at stride 1 a pixel's feature depends on that pixel alone, so masking the image
    # (Eq. 2) and pooling the whole image's feature map under the mask must agree exactly.
    cfg = PerceptionConfig(layers=((8, 1, 1), (8, 1, 1)), hidden=(16, 8))
    torch.manual_seed(1)
    net = PerceptionNet(cfg).eval()
    lab = _labels((40.0, 40.0))  # a corner of the grid in view: ~36 cells keep the literal pass short
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (1, 224, 224, 3), dtype=np.uint8)
    with torch.no_grad():
        pooled = net(img, lab)
        literal = net.forward_literal(img, lab)
    seen = cell_pooling(lab, 1).pixels[0] > 0
    assert 30 <= seen.sum() < 100
    assert torch.allclose(pooled[0, seen], literal[0, seen], atol=1e-4)


def test_cell_prediction_is_local():
    # Changing the pixels of one cell leaves far-away cells' outputs unchanged (receptive field ~ 20 px).
    torch.manual_seed(2)
    net = PerceptionNet().eval()
    lab = _labels((0.0, 0.0))
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (1, 224, 224, 3), dtype=np.uint8)
    img2 = img.copy()
    img2[0][lab[0].numpy() == 0] = 255  # paint the NW corner cell white
    with torch.no_grad():
        a, b = net(img, lab), net(img2, lab)
    assert not torch.allclose(a[0, 0], b[0, 0])
    assert torch.allclose(a[0, 55], b[0, 55], atol=1e-6)  # a cell in the middle of the grid


def test_outputs_shapes_and_heads():
    torch.manual_seed(3)
    net = PerceptionNet().eval()
    lab = _labels((0.0, 0.0), (0.0, 10.0), (-10.0, 0.0))
    img = np.zeros((3, 224, 224, 3), np.uint8)
    with torch.no_grad():
        out = net.forward_all(img, lab)
    assert out.log_probs.shape == (3, 100, 2)
    assert torch.allclose(out.log_probs.exp().sum(-1), torch.ones(3, 100), atol=1e-5)
    assert out.cell_features.shape == (3, 100, net.cfg.cell_dim)
    assert out.global_feature.shape == (3, net.cfg.global_dim)
    conf = ConfidenceNet(net.cfg.cell_dim)
    assert conf(out.cell_features).shape == (3, 100)
    emb = ImageEmbedding(net.cfg.global_dim)
    assert emb(out.global_feature).shape == (3, EMBED_DIM)


def test_checkpoint_round_trip(tmp_path):
    torch.manual_seed(4)
    cfg = PerceptionConfig(layers=((8, 3, 2), (16, 3, 2)), hidden=(32, 16))
    net = PerceptionNet(cfg).eval()
    path = save_perception(net, tmp_path / "p.pt", extra={"note": "x"})
    net2, extra = load_perception(path)
    assert extra["note"] == "x" and net2.cfg == cfg
    lab = _labels((0.0, 0.0))
    img = np.full((1, 224, 224, 3), 100, np.uint8)
    with torch.no_grad():
        assert torch.equal(net(img, lab), net2(img, lab))


def test_bad_inputs_are_clear_errors(tmp_path):
    net = PerceptionNet()
    with pytest.raises(UavsearchError, match="not found"):
        load_perception(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(UavsearchError, match="not a uavsearch perception checkpoint"):
        load_perception(tmp_path / "junk.pt")
    with pytest.raises(UavsearchError, match="do not match"):
        net(np.zeros((1, 224, 224, 3), np.uint8), _labels((0.0, 0.0), (0.0, 0.0)))
    with pytest.raises(UavsearchError, match="multiple of the feature stride"):
        cell_pooling(torch.zeros(1, 225, 224, dtype=torch.int16), 4)


def test_bits_dropout_keeps_one_minus_p_scales_by_its_inverse_and_is_identity_in_eval():
    from uavsearch.search.perception import BitsDropout

    torch.manual_seed(0)
    d = BitsDropout(0.3)
    x = torch.ones(400_000)
    y = d(x)
    kept = y != 0
    assert abs(kept.float().mean().item() - 0.7) < 0.003  # 0.7 +- 5 sigma at n = 4e5
    assert torch.allclose(y[kept], torch.full_like(y[kept], 1 / 0.7))
    torch.manual_seed(0)
    assert torch.equal(d(x), y)  # the global torch seed decides the mask
    x2 = torch.randn(3, 5, 7, requires_grad=True)  # odd sizes: the bit words do not divide the tensor
    out = d(x2)
    out.sum().backward()
    assert torch.equal(x2.grad != 0, out != 0)
    assert torch.equal(d.eval()(x2), x2) and torch.equal(BitsDropout(0.0)(x2), x2)
    assert torch.equal(BitsDropout(1.0)(x2), torch.zeros_like(x2))


def test_confidence_forward_rows_equals_the_net_on_the_gathered_rows_with_a_mask_per_copy():
    from uavsearch.search.perception import ConfidenceNet

    torch.manual_seed(0)
    conf = ConfidenceNet(7, dropout=0.5)
    feats = torch.randn(3, 10, 7)
    rows = torch.tensor([[0, 2, 2], [1, 0, 0]])
    conf.eval()
    assert torch.allclose(conf.forward_rows(feats, rows), conf(feats[rows]), atol=1e-6)
    conf.train()
    out = conf.forward_rows(feats, rows)
    assert out.shape == (2, 3, 10)
    assert not torch.equal(out[0, 1], out[0, 2])  # the same view in two places: two dropout draws


def test_a_net_across_altitudes_reads_the_altitude_and_refuses_to_guess_it(tmp_path):
    torch.manual_seed(0)
    cfg = PerceptionConfig(altitude_feature=True)
    assert cfg.cell_dim == PerceptionConfig().cell_dim + 1
    net = PerceptionNet(cfg).eval()
    img = torch.rand(2, 3, 224, 224)
    lab = _labels((0, 0), (5, 0))
    with pytest.raises(UavsearchError, match="altitude"):
        net.forward_all(img, lab)
    with pytest.raises(UavsearchError, match="positive"):
        net.forward_all(img, lab, altitude_m=[70.0, -1.0])
    with torch.no_grad():
        high = net.forward_all(img, lab, altitude_m=70.0)
        low = net.forward_all(img, lab, altitude_m=[40.0, 40.0])
    # the same pixels read at another altitude are another input: only the altitude column differs
    assert torch.equal(high.cell_features[..., :-1], low.cell_features[..., :-1])
    assert torch.allclose(high.cell_features[..., -1], torch.zeros(()))  # log(70 / 70)
    assert torch.allclose(low.cell_features[..., -1], torch.log(torch.tensor(40.0 / 70.0)))
    assert not torch.equal(high.log_probs, low.log_probs)
    # checkpoints keep it; a net of one altitude ignores the argument
    save_perception(net, tmp_path / "alt.pt")
    back, _ = load_perception(tmp_path / "alt.pt")
    assert back.cfg.altitude_feature
    with torch.no_grad():
        assert torch.equal(back.forward_all(img, lab, altitude_m=40.0).log_probs, low.log_probs)
    plain = PerceptionNet().eval()
    with torch.no_grad():
        assert torch.equal(plain.forward_all(img, lab).log_probs, plain.forward_all(img, lab, altitude_m=40.0).log_probs)
    assert not PerceptionConfig.from_dict({k: v for k, v in cfg.__dict__.items() if k != "altitude_feature"}).altitude_feature


def test_positive_crops_are_centred_on_an_occupied_cell_that_shows_a_person():
    from uavsearch.search.train.perception import positive_centres, random_crops

    lab = _labels((0, 0), (0, 0), (0, 0))
    pooling = cell_pooling(lab, 4)
    occ = np.zeros((3, 100), np.int8)
    occ[:, [11, 88]] = 1
    px = np.zeros((3, 100), np.int32)
    px[0, 88] = 5  # view 0: only cell 88 shows its person; view 1: nobody shows; view 2: not asked
    px[2, 11] = 5
    rng = np.random.default_rng(0)
    centres = positive_centres(rng, 2, occ, px, pooling)
    assert np.allclose(centres[0], pooling.centroid[0, 88].numpy()) and np.isnan(centres[1:]).all()
    image = np.repeat(lab.numpy()[..., None], 3, -1)
    crops = random_crops(rng, 96, 4, image, centres=centres)[0]
    assert crops.shape == (3, 96, 96, 3)
    assert (crops[0, 44:52, 44:52, 0] == 88).all()  # the cell sits at the window's centre
    assert positive_centres(rng, 0, occ, px, pooling) is None
