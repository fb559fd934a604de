"""Each fusion method on hand-made inputs whose fused result is computed by hand."""

import math

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.search.fusion import FUSIONS, FusionViews, LearnedFusion, fuse

# Three views (T = 3) of four cells (N = 4). Cell 3 is never seen; cell 2 is seen by views 0 and 2 only.
P = np.array(
    [
        [0.9, 0.2, 0.6, 0.7],
        [0.6, 0.4, 0.99, 0.7],
        [0.3, 0.1, 0.2, 0.7],
    ]
)
V = np.array(
    [
        [True, True, True, False],
        [True, True, False, False],
        [True, True, True, False],
    ]
)
AREA = np.array(
    [
        [100.0, 250.0, 180.0, 0.0],
        [300.0, 250.0, 999.0, 0.0],
        [120.0, 90.0, 200.0, 0.0],
    ]
)
PRIOR = 0.1


def logit(p):
    return math.log(p / (1 - p))


def test_average_by_hand():
    out = fuse("average", P, V, prior=PRIOR)
    assert out == pytest.approx([(0.9 + 0.6 + 0.3) / 3, (0.2 + 0.4 + 0.1) / 3, (0.6 + 0.2) / 2, PRIOR])


def test_bayes_log_odds_by_hand():
    l0 = logit(PRIOR)
    expect0 = l0 + sum(logit(p) - l0 for p in (0.9, 0.6, 0.3))
    expect2 = l0 + (logit(0.6) - l0) + (logit(0.2) - l0)
    out = fuse("bayes", P, V, prior=PRIOR)
    assert out[0] == pytest.approx(1 / (1 + math.exp(-expect0)))
    assert out[2] == pytest.approx(1 / (1 + math.exp(-expect2)))
    assert out[3] == pytest.approx(PRIOR)


def test_bayes_with_uniform_prior_multiplies_odds():
    # prior 0.5: odds multiply; 0.8 and 0.8 -> odds 4 * 4 = 16 -> 16/17.
    out = fuse("bayes", np.array([[0.8], [0.8]]), np.ones((2, 1), bool), prior=0.5)
    assert out[0] == pytest.approx(16 / 17)


def test_bayes_single_view_returns_that_view():
    out = fuse("bayes", P[:1], V[:1], prior=PRIOR)
    assert out[:3] == pytest.approx(P[0, :3])


def test_by_size_picks_largest_valid_view():
    out = fuse("size", P, V, area_px=AREA, prior=PRIOR)
    # cell 0: view 1 (300 px); cell 1: tie 250/250 -> earliest (view 0); cell 2: view 1 (999 px) is not
    # valid, so view 2 (200 px); cell 3: prior.
    assert out == pytest.approx([0.6, 0.2, 0.2, PRIOR])


def test_learned_softmax_weights_by_hand():
    s = np.array(
        [
            [0.0, 1.0, 2.0, 5.0],
            [math.log(2.0), 1.0, 50.0, 5.0],
            [math.log(3.0), 1.0, 2.0, 5.0],
        ]
    )
    out = fuse("learned", P, V, scores=s, prior=PRIOR)
    # cell 0: weights 1:2:3 -> (0.9 + 1.2 + 0.9) / 6; cell 1: equal scores -> mean; cell 2: view 1 (score 50)
    # is masked, equal weights on views 0 and 2; cell 3 never seen -> prior.
    assert out == pytest.approx([3.0 / 6, 0.7 / 3, 0.4, PRIOR])


def test_learned_is_differentiable_and_masked_views_get_no_gradient():
    p = torch.tensor(P, requires_grad=True)
    s = torch.zeros(3, 4, dtype=torch.float64, requires_grad=True)
    out = fuse("learned", p, torch.tensor(V), scores=s, prior=PRIOR)
    assert isinstance(out, torch.Tensor)
    torch.log(out[:3]).sum().backward()
    assert torch.isfinite(s.grad).all() and torch.isfinite(p.grad).all()
    assert s.grad[1, 2] == 0 and p.grad[1, 2] == 0  # cell 2 unseen in view 1
    assert (s.grad[:, 3] == 0).all()  # never-seen cell
    # Raising the score of the view with the highest p raises the fused p: gradient sign check for cell 0.
    assert s.grad[0, 0] > 0 and s.grad[2, 0] < 0


def test_oracle_correct_iff_any_view_correct():
    labels = np.array([0, 1, 1, 0])
    out = fuse("oracle", P, V, labels=labels, prior=PRIOR)
    # cell 0 (empty): min = 0.3 -> correct; cell 1 (occupied): max = 0.4 -> wrong (no view had > 0.5);
    # cell 2 (occupied): max over views 0, 2 = 0.6 (0.99 is masked); cell 3: prior.
    assert out == pytest.approx([0.3, 0.4, 0.6, PRIOR])


def test_variable_length_sequences_by_padding():
    # Batch of two sequences: the second has only one real view, padded with valid=False.
    p = np.stack([P, np.array([[0.8, 0.3, 0.1, 0.9], [0.5] * 4, [0.5] * 4])])
    v = np.stack([V, np.array([[True] * 4, [False] * 4, [False] * 4])])
    for method in ("bayes", "average", "learned"):
        kw = {"scores": np.zeros_like(p)} if method == "learned" else {}
        out = fuse(method, p, v, prior=PRIOR, **kw)
        assert out.shape == (2, 4)
        assert out[1] == pytest.approx([0.8, 0.3, 0.1, 0.9])
    out = fuse("size", p, v, area_px=np.ones_like(p), prior=PRIOR)
    assert out[1] == pytest.approx([0.8, 0.3, 0.1, 0.9])


def test_all_methods_torch_and_numpy_agree_and_never_nan():
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, (4, 5, 100))
    v = rng.uniform(size=(4, 5, 100)) < 0.6
    v[:, :, 0] = False  # a cell nobody saw
    kw = dict(area_px=rng.uniform(50, 300, p.shape), scores=rng.normal(size=p.shape), labels=rng.uniform(size=(4, 100)) < 0.1)
    for m in (m for m, cls in FUSIONS.items() if hasattr(cls, "kernel")):  # the functional forms
        a = fuse(m, p, v, **kw)
        b = fuse(m, torch.tensor(p), torch.tensor(v), **{k: torch.tensor(x) for k, x in kw.items()}).numpy()
        assert a == pytest.approx(b)
        assert not np.isnan(a).any() and ((a >= 0) & (a <= 1)).all()
        assert a[:, 0] == pytest.approx(0.1)


def test_prefixes_match_truncated_sequences():
    s = np.arange(12.0).reshape(3, 4)
    pre = LearnedFusion(prior=PRIOR).prefixes(FusionViews(torch.tensor(P), torch.tensor(V), scores=torch.tensor(s))).numpy()
    assert pre.shape == (3, 4)
    assert pre[1] == pytest.approx(fuse("learned", P[:2], V[:2], scores=s[:2], prior=PRIOR))
    assert pre[2] == pytest.approx(fuse("learned", P, V, scores=s, prior=PRIOR))


def test_bad_input_is_a_clear_error():
    with pytest.raises(UavsearchError, match="unknown fusion"):
        fuse("median", P, V)
    with pytest.raises(UavsearchError, match="needs scores"):
        fuse("learned", P, V)
    with pytest.raises(UavsearchError, match="needs labels"):
        fuse("oracle", P, V)
    with pytest.raises(UavsearchError, match="must both be"):
        fuse("average", P, V[:2])
    with pytest.raises(UavsearchError, match="prior"):
        fuse("average", P, V, prior=0.0)


def test_fusion_objects_step_by_step_equal_the_kernels_bit_for_bit():
    """update() view by view (what the loop does) and fuse() give exactly the functional kernels' maps (at one
    intra-op thread: with more, the confidence net's reductions may split differently for (B, 1, N) and (B, T, N)
    inputs, which changes the last bit; the thread count is restored after)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _step_by_step_equals_the_kernels()
    finally:
        torch.set_num_threads(threads)


def _step_by_step_equals_the_kernels():
    from uavsearch.search.perception import ConfidenceNet

    torch.manual_seed(0)
    B, T, N, D = 3, 5, 100, 6
    p, v = torch.rand(B, T, N), torch.rand(B, T, N) < 0.6
    area, feats, labels = torch.rand(B, T, N) * 300, torch.randn(B, T, N, D), torch.rand(B, N) < 0.1
    net = ConfidenceNet(D).eval()
    given = {"area_px": area, "scores": net(feats), "labels": labels}
    for name, cls in ((n, c) for n, c in FUSIONS.items() if hasattr(c, "kernel")):
        fusion = LearnedFusion(net) if name == "learned" else cls()
        views = FusionViews(p, v, area, feats, None, torch.zeros(B, T, dtype=torch.long), labels)
        state = fusion.init_state(B, N)
        for t in range(T):
            state, fused = fusion.update(state, views._replace(**{
                k: x[:, t:t + 1] for k, x in views._asdict().items() if x is not None and k != "labels"}))
            want = fuse(name, p[:, :t + 1], v[:, :t + 1], **{k: (x if k == "labels" else x[:, :t + 1])
                                                            for k, x in given.items() if k in cls.needs})
            assert torch.equal(fused, want), (name, t)
        assert torch.equal(fusion.fuse(views), want)
        assert torch.equal(fusion.prefixes(views)[:, -1], want)


def test_fusion_saves_itself_and_loads_back():
    from uavsearch.search.fusion import load_fusion

    torch.manual_seed(0)
    learned = LearnedFusion.new(6).eval()
    back = load_fusion(learned.save_dict())
    x = torch.randn(2, 5, 6)
    assert type(back) is LearnedFusion and torch.equal(back.scorer(x), learned.scorer(x))
    assert type(load_fusion(FUSIONS["size"]().save_dict())) is FUSIONS["size"]
    with pytest.raises(UavsearchError, match="unknown fusion"):
        load_fusion({"name": "median", "config": {}, "state_dict": {}})


def test_shipped_checkpoints_in_the_old_layout_still_load():
    """models/ holds checkpoints written before fusions saved themselves: they convert on load."""
    from uavsearch.paths import MODELS_DIR
    from uavsearch.search.policy import FORMAT_V1, load_search_model

    path = MODELS_DIR / "search_s2_learned.pt"
    ck = torch.load(path, map_location="cpu", weights_only=True)
    assert ck["format"] == FORMAT_V1
    fusion = load_search_model(path).fusion
    assert fusion.name == "learned" and fusion.trainable
    c = ck["confidence"]
    assert all(torch.equal(fusion.net.state_dict()[k], v.float()) for k, v in c["state_dict"].items())
    assert load_search_model(MODELS_DIR / "search_s2_bayes.pt").fusion.name == "bayes"


def test_calibrated_fusion_fits_an_overconfident_net_and_discounts_repeated_views():
    """Views of a net that says 0.8 for clutter as often as for people: after fitting, one such view leaves a
    cell below 0.5, a 0.99 view claims it, an unseen cell keeps the occupied share, and n equal views add
    n^(1 - gamma) times one view's evidence."""
    from uavsearch.search.fusion import CalibratedFusion, fusion_from_spec, load_fusion

    gen = torch.Generator().manual_seed(0)
    S, T, N = 40, 4, 200
    labels = torch.rand(S, N, generator=gen) < 0.05
    y = labels[:, None].expand(S, T, N)
    clutter = torch.rand(S, T, N, generator=gen) < 0.1
    p = torch.where(y, torch.full((S, T, N), 0.99), torch.where(clutter, 0.8, 0.05))
    p = torch.where(y & (torch.rand(S, T, N, generator=gen) < 0.5), torch.full_like(p, 0.8), p)
    area = torch.full((S, T, N), 100.0)
    valid = torch.ones(S, T, N, dtype=torch.bool)
    fit = CalibratedFusion.fit(FusionViews(p, valid, area, labels=labels))
    assert fit.prior == pytest.approx(labels.float().mean().item())

    def one(pv, n=1, gamma=0.0):
        f = CalibratedFusion(fit.coef, fit.prior, gamma)
        return f.fuse(FusionViews(torch.full((1, n, 1), pv), torch.ones(1, n, 1, dtype=torch.bool),
                                  torch.full((1, n, 1), 100.0))).item()

    assert one(0.8) < 0.5 < one(0.99)
    assert CalibratedFusion(fit.coef, fit.prior).fuse(FusionViews(
        torch.rand(1, 2, 3), torch.zeros(1, 2, 3, dtype=torch.bool), torch.ones(1, 2, 3)))[0].tolist() == \
        pytest.approx([fit.prior] * 3)
    l0, z = logit(fit.prior), logit(one(0.8))
    for gamma in (0.0, 0.5, 1.0):
        assert logit(one(0.8, 4, gamma)) == pytest.approx(l0 + 4 ** (1 - gamma) * (z - l0), rel=1e-4)
    # four far views (100 px) and one close look (400 px): only the far ones repeat one another
    mixed = CalibratedFusion(fit.coef, fit.prior, 0.5).fuse(FusionViews(
        torch.full((1, 5, 1), 0.8), torch.ones(1, 5, 1, dtype=torch.bool), torch.tensor([100.0] * 4 + [400.0])[None, :, None]))
    z_close = logit(CalibratedFusion(fit.coef, fit.prior).fuse(FusionViews(
        torch.full((1, 1, 1), 0.8), torch.ones(1, 1, 1, dtype=torch.bool), torch.full((1, 1, 1), 400.0))).item())
    assert logit(mixed.item()) == pytest.approx(l0 + 2 * (z - l0) + (z_close - l0), rel=1e-4)
    # view by view (what the loop does) gives exactly fuse() on the history, at mixed scales
    gen.manual_seed(1)
    b, t_max, n = 3, 7, 50
    views = FusionViews(torch.rand(b, t_max, n, generator=gen), torch.rand(b, t_max, n, generator=gen) < 0.7,
                        torch.tensor([50.0, 190.0, 600.0])[torch.randint(0, 3, (b, t_max, n), generator=gen)]
                        * (0.5 + torch.rand(b, t_max, n, generator=gen)))
    steps = CalibratedFusion(fit.coef, fit.prior, 0.5)
    state = None
    for t in range(t_max):
        state, fused = steps.update(state, FusionViews(*(x[:, t:t + 1] for x in views[:3])))
        assert torch.equal(fused, steps.fuse(FusionViews(*(x[:, :t + 1] for x in views[:3])))), t
    back = load_fusion(CalibratedFusion(fit.coef, fit.prior, 0.25).save_dict())
    assert (back.coef, back.prior, back.gamma, back.spec) == (fit.coef, fit.prior, 0.25, "calibrated:0.25")
    with pytest.raises(UavsearchError, match="fusion must be"):
        fusion_from_spec("calibrated", "fusion")  # its coefficients come from fitting, not from a name
    from uavsearch.search.agents import check_names

    with pytest.raises(UavsearchError, match="fitted on training views"):
        check_names("calibrated")  # a mission or env naming it would get Bayes' rule on raw p without a word
    with pytest.raises(UavsearchError, match="gamma"):
        CalibratedFusion(fit.coef, fit.prior, 2.0)
    with pytest.raises(UavsearchError, match="both occupied and empty"):
        CalibratedFusion.fit(FusionViews(p, valid, area, labels=torch.zeros(S, N, dtype=torch.bool)))


def test_the_numpy_kernels_equal_the_torch_ones_to_float32():
    """fuse_host (the envs' per-step fusion, numpy in the calling thread) gives fuse's maps after float32 rounding."""
    from uavsearch.search.fusion import FUSIONS, CalibratedFusion, FusionViews, LearnedFusion

    rng = np.random.default_rng(0)
    B, T, N = 16, 6, 200
    p, v = rng.random((B, T, N)), rng.random((B, T, N)) < 0.6
    v[:, :, :5] = False  # cells no view measured get the prior
    views = FusionViews(p, v, rng.random((B, T, N)) * 300, scores=rng.normal(size=(B, T, N)),
                        labels=rng.random((B, N)) < 0.2)
    methods = [FUSIONS[n]() for n in ("bayes", "average", "size", "oracle")] + [
        LearnedFusion(None), CalibratedFusion(), CalibratedFusion([1.1, 0.2, -0.3, 0.05], 0.07, 0.5)]
    for f in methods:
        want = f.fuse(FusionViews(*(None if x is None else torch.as_tensor(x) for x in views))).numpy()
        np.testing.assert_array_equal(f.fuse_host(views).astype(np.float32), want.astype(np.float32), err_msg=f.name)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("threads", [1, 2])
def test_the_log_odds_are_torch_logits_bits(dtype, threads):
    """The fusions' log-odds (outside torch's logit kernel, which stalls beside a busy process) are torch.logit's
    values to the bit, at one thread and at two, over the shapes the envs and the evaluation fuse."""
    from uavsearch.search.fusion import EPS, _logit

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        gen = torch.Generator().manual_seed(0)
        for shape in [(1, 1, 900), (1, 14, 900), (3, 8, 900), (256, 8, 100), (64, 30, 1600)]:
            p = torch.rand(shape, generator=gen, dtype=dtype)
            p[..., :5] = torch.tensor([0.0, 1.0, EPS / 2, 1 - EPS / 2, 0.5], dtype=dtype)
            assert torch.equal(_logit(p), torch.logit(p.clamp(EPS, 1.0 - EPS)))
    finally:
        torch.set_num_threads(before)
