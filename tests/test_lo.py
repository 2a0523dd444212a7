"""Local optimisation and scoring (rlsac.estimation.lo) on synthetic data with known answers."""

import math

import numpy as np
import pytest
import torch

from rlsac.config import build
from rlsac.data import lines
from rlsac.data.lines import LineDataConf
from rlsac.errors import RlsacError
from rlsac.estimation.baselines import finalize, ransac
from rlsac.estimation.lo import (
    SCORES,
    Best,
    LOConf,
    _gammainc,
    _magsac_loss,
    _magsac_weight,
    local_optimization,
    score,
    update_best,
)
from rlsac.estimation.sampling import gather_points, uniform_minimal_sets
from rlsac.maths import geometry
from rlsac.rl.env import EnvConf
from rlsac.rl.rollout import rlsac_estimate
from rlsac.tasks import get_task

LINE = get_task("line")
CONFS = [LOConf(enabled=True, score=s, iterations=3, inner_samples=k, threshold_scale=t)
         for s in SCORES for k, t in ((0, 1.0), (5, 2.0))]


def line_batch(rate=0.5, n=40, seed=0):
    d = lines.generate(build(LineDataConf, {"n_instances": n, "seed": seed, "outlier_rate": rate}))
    return d, lines.to_batch(d)


def noisy_line(n=50, sigma=0.02, seed=0):
    """Points on y = x / 2 + 1 (x in [0, 8]) with Gaussian noise: (1, n, 2)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.linspace(0, 8, n, dtype=torch.float64)
    pts = torch.stack([x, x / 2 + 1], -1) + sigma * torch.randn(n, 2, generator=g, dtype=torch.float64)
    return pts[None]


def same_line(a, b) -> float:
    """Distance between two (a, b, c) lines up to sign."""
    a, b = torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)
    return min((a - b).norm().item(), (a + b).norm().item())


@pytest.mark.parametrize("conf", CONFS, ids=lambda c: f"{c.score}-k{c.inner_samples}")
def test_lo_never_returns_a_worse_score(conf):
    _, b = line_batch()
    coords, mask = b["coords"], b["mask"]
    g = torch.Generator().manual_seed(1)
    hyp, valid = LINE.solve(gather_points(coords, uniform_minimal_sets(mask, 2, 1, g))[:, 0])
    s0 = score(LINE, conf, LINE.residuals(hyp, coords), mask)
    h, s, fits = local_optimization(LINE, conf, coords, mask, hyp, s0, g)
    assert fits == conf.inner_samples + conf.iterations
    assert (s >= s0).all()
    # the returned score is the returned hypothesis' score, and LO found something better somewhere
    np.testing.assert_allclose(s.numpy(), score(LINE, conf, LINE.residuals(h, coords), mask).numpy(), rtol=1e-9)
    assert (s > s0).sum() >= len(s0) // 4


@pytest.mark.parametrize("name", ["count", "msac"])
def test_lo_on_exact_inliers_reaches_the_least_squares_fit(name):
    coords = noisy_line()
    mask = torch.ones(1, 50, dtype=torch.bool)
    tls, _ = LINE.refine(coords, mask)  # every point is an inlier: the least-squares answer
    start, _ = LINE.solve(coords[:, [3, 40]])  # a minimal-sample line through two noisy points
    conf = LOConf(enabled=True, score=name, iterations=2)
    s0 = score(LINE, conf, LINE.residuals(start, coords), mask)
    assert s0.item() == pytest.approx(50.0, abs=20)  # count: all 50 inliers already; msac: < 50
    h, s, _ = local_optimization(LINE, conf, coords, mask, start, s0)
    assert same_line(h[0], tls[0]) < 1e-9 < same_line(start[0], tls[0])


def test_magsac_lo_on_exact_inliers_moves_towards_least_squares():
    coords = noisy_line(sigma=0.01)
    mask = torch.ones(1, 50, dtype=torch.bool)
    tls, _ = LINE.refine(coords, mask)
    start, _ = LINE.solve(coords[:, [3, 40]])
    conf = LOConf(enabled=True, score="magsac", iterations=6, sigma_scale=2.0)
    s0 = score(LINE, conf, LINE.residuals(start, coords), mask)
    h, s, _ = local_optimization(LINE, conf, coords, mask, start, s0)
    assert s.item() > s0.item()
    assert same_line(h[0], tls[0]) < 0.25 * same_line(start[0], tls[0])


def test_fundamental_lo_moves_towards_least_squares():
    torch.manual_seed(0)
    K = torch.tensor([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]], dtype=torch.float64)[None]
    a = 0.2
    R = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]],
                     dtype=torch.float64)[None]
    t = torch.tensor([[1.0, 0.1, 0.2]], dtype=torch.float64)
    X = torch.rand(1, 120, 3, dtype=torch.float64) * torch.tensor([4.0, 3, 4]) + torch.tensor([-2.0, -1.5, 5])
    x1 = X @ K[0].T
    x2 = (X @ R[0].T + t) @ K[0].T
    pts = torch.cat([x1[..., :2] / x1[..., 2:], x2[..., :2] / x2[..., 2:]], -1) + 0.3 * torch.randn(1, 120, 4,
                                                                                                       dtype=torch.float64)
    task = get_task("fundamental")
    mask = torch.ones(1, 120, dtype=torch.bool)
    ls, _ = geometry.eight_point(pts, mask)
    start, ok = task.solve(pts[:, :8])
    assert ok.item()
    conf = LOConf(enabled=True, score="magsac", iterations=4, sigma_scale=2.0)
    s0 = score(task, conf, task.residuals(start, pts), mask)
    h, s, _ = local_optimization(task, conf, pts, mask, start, s0)

    def dist(f):
        return min((f - ls).norm().item(), (f + ls).norm().item())

    assert s.item() > s0.item() and dist(h) < 0.5 * dist(start)


def test_lo_off_is_the_plain_ransac_loop_bit_for_bit():
    _, b = line_batch(rate=0.6, n=30, seed=3)
    coords, mask = b["coords"], b["mask"]
    g = torch.Generator().manual_seed(5)
    # the loop as it was before rlsac.estimation.lo existed (chunks of 64 here, so the best is folded across chunks)
    best_h, best_c = None, torch.full((30,), -1, dtype=torch.long)
    for start in range(0, 150, 64):
        k = min(64, 150 - start)
        hyps, valid = LINE.solve(gather_points(coords, uniform_minimal_sets(mask, 2, k, g)).flatten(0, 1))
        count = ((LINE.residuals(hyps, coords.repeat_interleave(k, 0)).view(30, k, -1) <= 0.1) & mask[:, None]).sum(-1)
        c, j = count.masked_fill(~valid.view(30, k), -1).max(1)
        h = hyps.view(30, k, 3)[torch.arange(30), j]
        better = c > best_c
        best_h = h if best_h is None else torch.where(better[:, None], h, best_h)
        best_c = torch.where(better, c, best_c)
    want = finalize(LINE, coords, mask, best_h, best_c >= 2)
    for lo in (None, LOConf(enabled=False, score="magsac", iterations=9)):
        got = ransac(LINE, b, 150, torch.Generator().manual_seed(5), chunk=64, lo=lo)
        assert set(got) == set(want) | {"hypotheses"} and got["hypotheses"].tolist() == [150] * 30
        for key in want:
            assert torch.equal(got[key], want[key]), key


def test_update_best_counts_the_lo_budget_and_keeps_the_best():
    _, b = line_batch(n=8)
    coords, mask = b["coords"], b["mask"]
    g = torch.Generator().manual_seed(0)
    conf = LOConf(enabled=True, score="msac", iterations=3, inner_samples=2)
    best = Best.empty(8, "cpu")
    for step in range(3):
        idx = uniform_minimal_sets(mask, 2, 5, g)
        hyps, valid = LINE.solve(gather_points(coords, idx).flatten(0, 1))
        res = LINE.residuals(hyps, coords.repeat_interleave(5, 0)).view(8, 5, -1)
        count = ((res <= 0.1) & mask[:, None]).sum(-1).masked_fill(~valid.view(8, 5), -1)
        before = best.score.clone()
        best = update_best(LINE, conf, coords, mask, best, hyps.view(8, 5, 3), count, res, g)
        assert (best.score >= before).all()
        if step == 0:  # every instance improves on "nothing yet": one LO call each
            assert best.lo_calls.tolist() == [1] * 8 and best.lo_fits.tolist() == [5] * 8
    assert (best.lo_fits == 5 * best.lo_calls).all() and best.lo_seconds > 0
    np.testing.assert_allclose(best.score.numpy(), score(LINE, conf, LINE.residuals(best.hyp, coords), mask).numpy())


def test_magsac_loss_closed_form():
    x = torch.linspace(0, 7, 200, dtype=torch.float64)
    for a in (0.5, 1.0, 1.5, 2.0, 2.5):
        np.testing.assert_allclose(_gammainc(a, x).numpy(), torch.special.gammainc(torch.full_like(x, a), x).numpy(),
                                   atol=1e-12)
    a0, a1, xk = 1.5, 2.5, 3.6437 ** 2 / 2  # dof 4, OpenCV's k
    xs = torch.linspace(0.01, xk - 0.01, 50, dtype=torch.float64).requires_grad_()
    rho = _magsac_loss(xs, a0, a1, xk)
    (grad,) = torch.autograd.grad(rho.sum(), xs)
    w = _magsac_weight(xs.detach(), a0, xk)
    np.testing.assert_allclose((grad / grad[0]).numpy(), (w / w[0]).numpy(), rtol=1e-6)  # weight = rho'
    assert _magsac_loss(torch.tensor([0.0], dtype=torch.float64), a0, a1, xk).item() == 0.0
    assert _magsac_weight(torch.tensor([0.0, xk, 2 * xk], dtype=torch.float64), a0, xk).tolist() == [1.0, 0.0, 0.0]
    # the quality of a perfect fit is the number of valid points, of a far one zero
    conf = LOConf(enabled=True, score="magsac")
    res = torch.tensor([[0.0, 0.0, 5.0, float("inf")]])
    assert score(LINE, conf, res, torch.tensor([[True, True, True, False]])).item() == pytest.approx(2.0)


def test_weighted_line_refit_known_answers():
    x = torch.linspace(0, 8, 6)
    coords = torch.cat([torch.stack([x, 0.5 * x + 1], -1), torch.tensor([[1.0, 9.0], [7.0, 0.5]])])[None]
    mask = torch.tensor([[True] * 6 + [False] * 2])
    a, ok_a = LINE.refine(coords, mask)
    b, ok_b = LINE.refine(coords, mask.double() * 3.0)  # a common scale does not change the fit
    assert ok_a.item() and ok_b.item() and same_line(a[0], b[0]) < 1e-6
    r5 = math.sqrt(5)
    assert same_line(a[0], [1 / r5, -2 / r5, 2 / r5]) < 1e-6
    # an integer weight equals repeating the point
    w = torch.tensor([[1.0, 1, 1, 1, 1, 1, 2, 0]])
    rep = torch.cat([coords, coords[:, 6:7]], 1)
    m = torch.tensor([[True] * 7 + [False, True]])
    assert same_line(LINE.refine(coords, w)[0][0], LINE.refine(rep, m)[0][0]) < 1e-5
    assert not LINE.refine(coords, torch.tensor([[0.5, 0, 0, 0, 0, 0, 0, 0]]))[1].item()  # one weighted point


def test_environment_with_lo_reports_its_budget_and_scores_at_least_as_well():
    _, b = line_batch(rate=0.6, n=16, seed=2)
    conf = LOConf(enabled=True, score="msac", iterations=2)
    env = EnvConf(steps_per_episode=5, lo=conf)
    out = rlsac_estimate(LINE, b, None, 20, env, generator=torch.Generator().manual_seed(0))
    plain = rlsac_estimate(LINE, b, None, 20, EnvConf(steps_per_episode=5), generator=torch.Generator().manual_seed(0))
    assert (out["lo_calls"] >= 2).all() and (out["lo_fits"] == 2 * out["lo_calls"]).all()  # >= 1 step + the final
    s_lo = score(LINE, conf, LINE.residuals(out["hyp"], b["coords"]), b["mask"])
    s_plain = score(LINE, conf, LINE.residuals(plain["hyp"], b["coords"]), b["mask"])
    assert s_lo.sum() > s_plain.sum()
    assert "lo_calls" not in plain


def test_lo_conf_checks():
    with pytest.raises(RlsacError, match="LO score"):
        LOConf(score="ransac")
    with pytest.raises(RlsacError, match="threshold_scale"):
        LOConf(threshold_scale=0.5)
    with pytest.raises(RlsacError, match="dof"):
        LOConf(dof=1)
    with pytest.raises(RlsacError, match="residuals"):
        update_best(LINE, LOConf(enabled=True), torch.zeros(2, 5, 2), torch.ones(2, 5, dtype=torch.bool),
                    Best.empty(2, "cpu"), torch.zeros(2, 3, 3), torch.zeros(2, 3, dtype=torch.long))


def test_table1_lo_rows_gap_and_pairs(workdir):
    import json

    import pandas as pd

    from rlsac.reports import tables

    ev = workdir / "ev" / "lines"
    values = {"ransac": 0.70, "oracle": 0.80, "ransac-lo": 0.75, "ours-lo": 0.82, "ours": 0.72}
    for d, v in values.items():
        for r, shift in ((0.5, 0.0), (0.1, 0.098)):  # o=0.1: RANSAC 0.798 vs Oracle 0.898 ... shifted alike
            p = ev / d / f"o{r:g}"
            p.mkdir(parents=True)
            (p / "summary.json").write_text(json.dumps({"mAA": v + shift, "median_deg": 0.1, "n_instances": 4}))
    (ev / "oracle" / "o0.1" / "summary.json").write_text(json.dumps({"mAA": 0.801, "median_deg": 0.1}))  # tiny gap
    for d, errs in (("ransac", [0.02, 0.02, 1.0, 1.0]), ("ransac-lo", [0.02, 0.02, 0.02, 1.0]),
                    ("ours-lo", [0.02] * 4)):
        pd.DataFrame({"instance": range(4), "err_deg": errs}).to_csv(ev / d / "o0.5" / "errors.csv", index=False)
    df = tables.table1("ev", "out")
    assert {"RANSAC-LO (not in the paper)", "Ours-LO (not in the paper)"} <= set(df["method"])
    assert set(df.loc[df["method"].str.contains("-LO"), "source"]) == {"ours"}
    gap = df.attrs["gap"].set_index("method")
    assert gap.loc["RANSAC-LO (not in the paper)", "o=0.5"] == "50%"
    assert gap.loc["Ours-LO (not in the paper)", "o=0.5"] == "120%"
    assert gap.loc["Ours", "o=0.5"] == "20%" and gap.loc["Ours", "o=0.1"] == "–"  # gap 0.003: not shared out
    paired = df.attrs["paired"].set_index("comparison")
    assert paired.loc["Ours-LO − RANSAC-LO", "o=0.5"].startswith("+0.250 [")
    assert paired.loc["Ours-LO − RANSAC", "o=0.5"].startswith("+0.500 [")
    assert "RANSAC → Oracle" in (workdir / "out" / "table1_lines.md").read_text()


def test_evaluate_lo_methods_report_their_budget(workdir):
    from rlsac.evaluation.evaluate import evaluate

    d = lines.generate(build(LineDataConf, {"n_instances": 12, "seed": 4, "outlier_rate": 0.5}))
    path = lines.write(workdir / "l.h5", d, build(LineDataConf, {"n_instances": 12, "seed": 4}))
    lo = {"score": "msac", "iterations": 2}
    s = evaluate({"task": "line", "method": "ransac-lo", "data": str(path), "iterations": 20, "lo": lo,
                  "out_dir": "a"}, track=False)
    assert s["lo"]["enabled"] and s["lo"]["score"] == "msac"
    assert s["lo_fits_per_instance"] == 2 * s["lo_calls_per_instance"] >= 4  # >= 1 improvement + the final
    u = evaluate({"task": "line", "method": "uniform-lo", "data": str(path), "iterations": 20, "lo": lo,
                  "steps_per_episode": 5, "out_dir": "b"}, track=False)
    assert u["lo_calls_per_instance"] >= 2 and 0 < u["lo_time_fraction"] < 1
    plain = evaluate({"task": "line", "method": "ransac", "data": str(path), "iterations": 20, "lo": lo,
                      "out_dir": "c"}, track=False)
    assert "lo_calls_per_instance" not in plain  # the options are ignored by methods without LO
    with pytest.raises(RlsacError, match="unknown config key"):
        evaluate({"task": "line", "method": "ransac-lo", "data": str(path), "lo": {"bogus": 1}}, track=False)
    with pytest.raises(RlsacError, match="needs --checkpoint"):
        evaluate({"task": "line", "method": "rlsac-lo", "data": str(path)}, track=False)


def test_trigger_minimal_optimises_every_new_best_minimal_hypothesis():
    coords = noisy_line(sigma=0.02)
    mask = torch.ones(1, 50, dtype=torch.bool)
    # candidates in order: a poor line, a better one (both minimal samples through data points), a worse one
    hyps = torch.stack([LINE.solve(coords[:, [0, 3]])[0], LINE.solve(coords[:, [5, 45]])[0],
                        LINE.solve(coords[:, [1, 2]])[0]], 1)  # (1, 3, 3)
    res = torch.stack([LINE.residuals(hyps[:, i], coords) for i in range(3)], 1)  # (1, 3, 50)
    count = ((res <= 0.1) & mask[:, None]).sum(-1)
    out = {}
    for trig in ("best", "minimal"):
        conf = LOConf(enabled=True, score="msac", iterations=2, trigger=trig)
        best = Best.empty(1, "cpu")
        scores = []
        for i in range(3):  # one candidate per update, as a sequential sampler
            best = update_best(LINE, conf, coords, mask, best, hyps[:, i:i + 1], count[:, i:i + 1], res[:, i:i + 1])
            scores.append(best.score.item())
        assert scores == sorted(scores)  # the stored best never gets worse
        out[trig] = best
    # "best": the LO'd first line already beats the raw second one, so LO ran once; "minimal": twice (1st, 2nd)
    assert out["best"].lo_calls.item() == 1 and out["minimal"].lo_calls.item() == 2
    raw = score(LINE, LOConf(score="msac"), res, mask[:, None])[0]
    assert out["minimal"].raw.item() == pytest.approx(raw.max().item()) and raw[1] == raw.max()


@pytest.mark.parametrize("name", SCORES)
def test_score_makes_its_tensors_on_the_residuals_device(name):
    """Every tensor score() makes is on the residuals' device. CI has no GPU: the meta device stands in for cuda
    (an operation that mixes a meta tensor with a CPU one of more than zero dimensions raises, as cuda's does)."""
    res = torch.tensor([[0.0, 0.5, 5.0, float("inf")]], device="meta")
    mask = torch.ones(1, 4, dtype=torch.bool, device="meta")
    out = score(LINE, LOConf(enabled=True, score=name), res, mask)
    assert out.device.type == "meta" and out.shape == (1,)
