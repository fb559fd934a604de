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


# --------------------------------------------------------------------------------------------------
# The contract and the registry


def _blocky_views(n: int, seed: int = 0) -> np.ndarray:
    """(n, 224, 224, 3) uint8 images of random 8 x 8 px blocks: fixed, cheap, and far from saturating a net."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (n, 28, 28, 3), dtype=np.uint8).repeat(8, 1).repeat(8, 2)


@pytest.mark.parametrize("kind,altitude", [("cnn", False), ("resnet", True)])  # the CNN's altitude: test above
def test_every_kind_keeps_the_contract(kind, altitude):
    from uavsearch.search.perception import Perception, TrainablePerception, ViewOutputs, build_perception

    torch.manual_seed(0)
    net = build_perception(kind, altitude_feature=altitude).eval()
    assert isinstance(net, Perception) and isinstance(net, TrainablePerception) and net.kind == kind
    assert net.num_cells == 100 and net.reads_altitude == altitude and 224 % net.stride == 0
    img, lab = _blocky_views(2), _labels((0.0, 0.0), (10.0, -10.0))
    with torch.no_grad():
        out = net.forward_all(img, lab, altitude_m=[70.0, 40.0])
    assert isinstance(out, ViewOutputs)
    assert out.log_probs.shape == (2, 100, 2) and out.log_probs.dtype == torch.float32
    assert out.cell_features.shape == (2, 100, net.cell_dim) and out.cell_features.dtype == torch.float32
    assert out.global_feature.shape == (2, net.global_dim) and out.global_feature.dtype == torch.float32
    assert out.cell_pixels.shape == (2, 100) and torch.equal(out.cell_pixels, cell_pooling(lab, 4).pixels)
    for t in (out.log_probs, out.cell_features, out.global_feature):
        assert torch.isfinite(t).all()
    assert torch.allclose(out.log_probs.exp().sum(-1), torch.ones(2, 100), atol=1e-5)
    # the same weights read a 30 x 30 grid
    wide = net.for_grid(900)
    assert wide.num_cells == 900 and net.num_cells == 100
    wide_lab = torch.as_tensor(cell_label_image(Grid(30, 5.0), INTR, nadir_camera_pose([0.0, 0.0, 70.0])))[None]
    with torch.no_grad():
        assert wide.forward_all(img[:1], wide_lab, altitude_m=70.0).log_probs.shape == (1, 900, 2)
    # the training side: a dense loss against a person map, a calibration shift that moves every margin
    net.train()
    out = net.forward_all(img, lab, altitude_m=70.0)
    loss = net.dense_loss(out, np.zeros((2, 224, 224), np.uint8), 20.0)
    assert loss.dim() == 0 and torch.isfinite(loss)
    loss.backward()
    net.eval()
    with torch.no_grad():
        before = net.forward_all(img, lab, altitude_m=70.0).log_probs
        net.shift_logit_margin(1.0)
        after = net.forward_all(img, lab, altitude_m=70.0).log_probs
    margin = lambda lp: lp[..., 1] - lp[..., 0]  # noqa: E731
    assert torch.allclose(margin(after) - margin(before), torch.ones(2, 100), atol=1e-4)


@pytest.mark.parametrize("kind", ["cnn", "resnet"])
def test_a_checkpoint_records_its_kind_and_rebuilds_the_same_net(tmp_path, kind):
    from uavsearch.search.perception import build_perception

    torch.manual_seed(5)
    net = build_perception(kind, altitude_feature=True, num_cells=100, hidden=(32, 16)).eval()
    path = save_perception(net, tmp_path / f"{kind}.pt", extra={"note": kind})
    assert torch.load(path, weights_only=True)["kind"] == kind
    back, extra = load_perception(path)
    assert type(back) is type(net) and back.kind == kind and extra["note"] == kind
    assert back.arguments() == net.arguments() and back.cfg == net.cfg
    img, lab = _blocky_views(2, seed=1), _labels((0.0, 0.0), (0.0, 10.0))
    with torch.no_grad():
        a, b = net.forward_all(img, lab, altitude_m=50.0), back.forward_all(img, lab, altitude_m=50.0)
    for f in ("log_probs", "cell_features", "global_feature", "cell_pixels"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def test_unknown_kinds_and_arguments_are_clear_errors(tmp_path):
    from uavsearch.search.perception import PerceptionNet, build_perception, register_perception

    with pytest.raises(UavsearchError, match="unknown perception kind 'vgg'.*cnn, detector, resnet"):
        build_perception("vgg")
    with pytest.raises(UavsearchError, match="no argument.*layers"):
        build_perception("resnet", layers=((8, 3, 2),))
    with pytest.raises(UavsearchError, match="registered twice"):
        register_perception("cnn")(type("Other", (PerceptionNet,), {}))
    net = build_perception("resnet")
    save_perception(net, tmp_path / "r.pt")
    ckpt = torch.load(tmp_path / "r.pt", weights_only=True)
    torch.save({**ckpt, "kind": "vgg"}, tmp_path / "vgg.pt")
    with pytest.raises(UavsearchError, match="unknown perception kind 'vgg'"):
        load_perception(tmp_path / "vgg.pt")
    # a fine-tuning start must be the same kind and architecture
    from uavsearch.search.train.perception import init_from

    with pytest.raises(UavsearchError, match="--init .*differs"):
        init_from(build_perception("cnn"), tmp_path / "r.pt")
    other = build_perception("resnet", altitude_feature=True)
    init_from(other, tmp_path / "r.pt")  # widened: the new altitude input starts at zero
    with torch.no_grad():
        img, lab = _blocky_views(1), _labels((0.0, 0.0))
        assert torch.allclose(net.eval().forward_all(img, lab).log_probs,
                              other.eval().forward_all(img, lab, altitude_m=40.0).log_probs, atol=1e-6)


# The shipped nets' outputs on the fixed input below, computed before perception had kinds: a checkpoint
# without a kind must stay the very same CNN. Per view: sums of log p(1), log p(0), cell features, global
# feature and cell pixels, then (view, cell, log p(1)) of a few cells in view.
SHIPPED_REFERENCE = {
    "perception.pt": (Grid(10, 5.0), [(0.0, 0.0, 70.0), (10.0, -10.0, 70.0)], {
        "lp1": [-491.8141266107559, -495.0906308889389], "lp0": [-1.5879812681814656, -1.3902647927752696],
        "cf": [3022.6398348617786, 3095.711212177902], "gf": [75.73706882815168, 77.81037284880586],
        "px": [19044.0, 19321.0]},
        [(0, 0, -6.045841693878174), (0, 37, -4.534799575805664), (0, 10, -1.9763318300247192),
         (1, 99, -5.175132751464844), (1, 53, -1.8828095197677612)]),
    "perception_wide.pt": (Grid(30, 5.0), [(0.0, 0.0, 70.0), (25.0, -25.0, 40.0)], {
        "lp1": [-1425.091446697712, -580.4551620483398], "lp0": [-760.3653723297175, -1204.1724287164398],
        "cf": [4491.169340306242, -1154.223627915248], "gf": [72.41766035829642, 69.67274271049246],
        "px": [50176.0, 50176.0]},
        [(0, 186, -1.1138288974761963), (0, 713, -0.7451930642127991), (1, 465, -4.034978866577148),
         (1, 469, -2.2904157638549805)]),
}


@pytest.mark.parametrize("name", sorted(SHIPPED_REFERENCE))
def test_the_shipped_nets_load_as_the_cnn_with_the_outputs_they_always_gave(name):
    from uavsearch.paths import MODELS_DIR

    grid, poses, sums, cells = SHIPPED_REFERENCE[name]
    ckpt = torch.load(MODELS_DIR / name, weights_only=True)
    assert "kind" not in ckpt  # written before kinds: loads as the CNN
    net, _ = load_perception(MODELS_DIR / name)
    assert net.kind == "cnn" and isinstance(net, PerceptionNet)
    lab = np.stack([cell_label_image(grid, INTR, nadir_camera_pose(list(p))) for p in poses])
    with torch.no_grad():
        o = net.forward_all(_blocky_views(len(poses)), lab, altitude_m=[p[2] for p in poses])
    got = {"lp1": o.log_probs[..., 1].double().sum(1), "lp0": o.log_probs[..., 0].double().sum(1),
           "cf": o.cell_features.double().sum((1, 2)), "gf": o.global_feature.double().sum(1),
           "px": o.cell_pixels.double().sum(1)}
    for k, ref in sums.items():
        assert np.allclose(got[k].numpy(), ref, rtol=1e-6, atol=1e-6), (k, got[k].tolist(), ref)
    for b, c, ref in cells:
        assert abs(float(o.log_probs[b, c, 1]) - ref) < 1e-6, (b, c)


def test_perceive_is_the_single_view_step_of_live_search_and_replay():
    from uavsearch.search.perception import build_perception, perceive
    from uavsearch.search.search_loop import observe_view
    from uavsearch.search.views import make_view

    torch.manual_seed(0)
    net = build_perception("resnet", altitude_feature=True).eval()
    imgs = _blocky_views(2, seed=3)
    views = [make_view(imgs[i], nadir_camera_pose([x, 0.0, z]), GRID, INTR, min_cell_area_px=20.0)
             for i, (x, z) in enumerate(((0.0, 70.0), (10.0, 40.0)))]
    o, valid, area = perceive(net, views)
    with torch.no_grad():
        ref = net.forward_all(imgs, np.stack([v.cell_label for v in views]), altitude_m=[70.0, 40.0])
    assert torch.equal(o.log_probs, ref.log_probs) and torch.equal(o.cell_features, ref.cell_features)
    assert torch.equal(valid, torch.as_tensor(np.stack([v.cells_in_view for v in views])) & (ref.cell_pixels > 0))
    assert area.dtype == torch.float32 and torch.equal(area[1], torch.as_tensor(views[1].cell_area_px))
    one = observe_view(net, views[1])
    assert torch.equal(one.log_probs, o.log_probs[1:]) and torch.equal(one.valid, valid[1:])


def _tiny_view_set(positions, seed: int):
    """A few views of the paper's grid with random pictures and people: enough for stage 1 to take steps."""
    from uavsearch.search.data.dataset import ViewSet

    rng = np.random.default_rng(seed)
    V = len(positions)
    labels = np.stack([cell_label_image(GRID, INTR, nadir_camera_pose([x, y, 70.0])) for x, y in positions])
    occ = (rng.random((V, 100)) < 0.1).astype(np.int8)
    person = np.zeros((V, 224, 224), np.uint8)
    for v in range(V):
        for c in np.flatnonzero(occ[v]):
            ys, xs = np.nonzero(labels[v] == c)
            if len(ys):
                person[v, ys[len(ys) // 2], xs[len(xs) // 2]] = 255
    px = np.stack([np.bincount(lab[lab >= 0].ravel(), minlength=100) for lab in labels]).astype(np.float32)
    return ViewSet(images=_blocky_views(V, seed), label_id=np.arange(V), labels=labels.astype(np.int16),
                   lattice_index=np.arange(V, dtype=np.int16),
                   position_enu=np.array([[x, y, 70.0] for x, y in positions], np.float32), cell_area_px=px,
                   cells_in_view=px > 0, person_px=occ * (px > 0).astype(np.int32),
                   occupancy=occ, scene_seed=np.full(V, seed, np.int64), occupied_cells=occ.sum(1).astype(np.int64),
                   person_frac=person)


def test_train_perception_with_net_resnet_writes_a_checkpoint_of_that_kind(tmp_path):
    from uavsearch.cli import build_parser
    from uavsearch.cli_args import dataclass_from_args
    from uavsearch.search.perception import ResNetPerception
    from uavsearch.search.train.perception import Args, train

    ns = build_parser("train").parse_args(
        ["train", "perception", "--net", "resnet", "--steps", "2", "--batch-size", "2", "--crop", "64",
         "--eval-every", "2", "--runs-dir", str(tmp_path / "runs"), "--out", str(tmp_path / "r.pt"), "--no-progress"])
    args = dataclass_from_args(Args, ns)
    assert args.net == "resnet" and dataclass_from_args(Args, build_parser("train").parse_args(
        ["train", "perception"])).net == "cnn"
    views = (_tiny_view_set([(0.0, 0.0), (10.0, 0.0), (0.0, -10.0)], 1), _tiny_view_set([(0.0, 0.0), (-10.0, 0.0)], 2), 0)
    rep = train(args, views=views)
    assert rep["train_views"] == 3 and 0.0 <= rep["eval/cell_ap"] <= 1.0
    net, extra = load_perception(tmp_path / "r.pt")
    assert isinstance(net, ResNetPerception) and net.kind == "resnet" and extra["args"]["net"] == "resnet"
    with torch.no_grad():
        assert torch.isfinite(net.forward_all(views[1].images, views[1].labels).log_probs).all()


def test_altitudes_may_come_as_a_tensor_and_stay_in_torch():
    # numpy never touches a tensor of altitudes (np.asarray of a CUDA tensor raises): the same values either way
    from uavsearch.search.perception import PooledPerception, build_perception

    alt = torch.tensor([70.0, 40.0], dtype=torch.float64)
    assert torch.equal(PooledPerception.altitudes(alt, 2), torch.tensor([70.0, 40.0]))
    assert PooledPerception.altitudes(torch.tensor(55.0), 3).tolist() == [55.0] * 3
    net = build_perception("cnn", altitude_feature=True).eval()
    img, lab = _blocky_views(2), _labels((0.0, 0.0), (0.0, 10.0))
    with torch.no_grad():
        assert torch.equal(net.forward_all(img, lab, altitude_m=alt).log_probs,
                           net.forward_all(img, lab, altitude_m=[70.0, 40.0]).log_probs)


def test_test_time_flips_average_the_four_mirrored_views(tmp_path):
    """`flips:PATH` is the net on the view and its three mirror images (image and cell labels mirrored together),
    the per-cell probabilities and features averaged; its caches are keyed apart from the plain net's."""
    from uavsearch.search.perception import FLIPS, FLIPS_PREFIX, load_perception, perception_tag, save_perception

    torch.manual_seed(0)
    path = save_perception(PerceptionNet(PerceptionConfig(num_cells=16)), tmp_path / "p.pt")
    plain, _ = load_perception(path)
    flipped, extra = load_perception(FLIPS_PREFIX + str(path))
    assert extra["test_time_flips"] == 4 and perception_tag(flipped) != perception_tag(plain)
    x = torch.rand(2, 3, 64, 64)
    lab = torch.randint(-1, 16, (2, 64, 64))
    with torch.no_grad():
        got = flipped.forward_all(x, lab)
        seen = [plain.forward_all(x.flip(d) if d else x, lab.flip(ld) if d else lab) for d, ld in FLIPS]
    p = torch.stack([o.log_probs.exp() for o in seen]).mean(0)
    assert torch.allclose(got.log_probs.exp(), p, atol=1e-6)
    assert torch.allclose(got.cell_features, torch.stack([o.cell_features for o in seen]).mean(0), atol=1e-6)
    sym_x = (x + x.flip(3)) + (x + x.flip(3)).flip(2)  # a view equal to its mirror images: the plain net's output
    sym_lab = torch.full((2, 64, 64), -1)
    sym_lab[:, 24:40, 24:40] = 5
    with torch.no_grad():
        assert torch.allclose(flipped.forward_all(sym_x, sym_lab).log_probs, plain.forward_all(sym_x, sym_lab).log_probs,
                              atol=1e-5)
