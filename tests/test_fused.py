"""The fused VN edge kernels (efem_viz/prior/fused.py, vn_kernels.cpp) against their eager references and the
encoder's original per-edge formulation, plus the cases the kernels must refuse or leave to the references."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from efem_viz.prior import fused
from efem_viz.prior.decoder import SDFDecoder
from efem_viz.prior.encoder import _gather
from efem_viz.prior.model import PriorConfig, ShapePrior
from efem_viz.prior.vn_layers import VNLinearLeakyReLU

needs_kernels = pytest.mark.skipif(not fused.load(), reason="the fused kernels could not be built here")


def _edge_inputs(seed: int, b: int = 3, ns: int = 40, nd: int = 20, k: int = 7, c: int = 12
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    f_src = torch.randn(b, ns, 3, c, generator=g)
    f_dst = torch.randn(b, nd, 3, c, generator=g)
    nbr = torch.randint(0, ns, (b, nd, k), generator=g)
    return f_src, f_dst, nbr


def test_rewritten_edge_mean_equals_the_per_edge_layer_in_float64() -> None:
    """mean_k VNLA([f_j − f_i ; f_i]) computed per edge (the spec's form) equals the rewritten reference, which
    moves both matrix products off the k-fold tensor."""
    layer = VNLinearLeakyReLU(2 * 12, 12).double()
    f_src, f_dst, nbr = (t.double() if t.is_floating_point() else t for t in _edge_inputs(0))
    fj = _gather(f_src, nbr)
    fi = f_dst[:, :, None].expand_as(fj)
    spec = layer(torch.cat([fj - fi, fi], dim=-1)).mean(dim=2)
    w = layer.lin.weight
    w1 = w[:, :12]
    with torch.no_grad():
        out = fused.edge_mean(F.linear(f_src, w1), F.linear(f_dst, w[:, 12:] - w1), nbr, layer.act.lin_dir.weight,
                              layer.act.negative_slope)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, spec.detach(), rtol=0, atol=1e-12)


@needs_kernels
@pytest.mark.parametrize("seed", [0, 1])
def test_edge_kernel_matches_the_reference(seed: int) -> None:
    f_src, f_dst, nbr = _edge_inputs(seed, c=13)
    a, c = torch.randn_like(f_src), torch.randn_like(f_dst)
    da, dc = torch.randn_like(a), torch.randn_like(c)
    da[0, 0, :, :] = 0.0  # zero directions: the floor of the norm, as in the reference
    ref = fused.edge_mean_reference(a, c, da, dc, nbr, 0.2)
    got = torch.ops.efem_vn.edge_mean(a, c, da, dc, nbr, 0.2)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)
    x = torch.randn(2, 9, 5, 3, 16)
    d = torch.randn_like(x)
    torch.testing.assert_close(torch.ops.efem_vn.act_mean(x, d, 0.2), fused.act_mean_reference(x, d, 0.2),
                               rtol=1e-5, atol=1e-5)


@needs_kernels
@pytest.mark.parametrize(("c", "c_in"), [(16, 3), (13, 3), (32, 5)])
def test_first_layer_kernel_matches_its_products_and_activation(c: int, c_in: int) -> None:
    """`fused.lin_act_mean` in one pass (the encoder's first layer: both products per edge, never in memory)
    equals the eager products, activation and mean to float32 rounding (widths on and off the vector lanes), a
    zero edge included; bad shapes are refused."""
    g = torch.Generator().manual_seed(c)
    x = torch.randn(3, 11, 7, 3, c_in, generator=g)
    x[0, 0, 0] = 0.0  # a zero edge: zero products, the direction's floor
    w, u = torch.randn(c, c_in, generator=g), torch.randn(c, c, generator=g)
    y = F.linear(x.double(), w.double())
    want = fused.act_mean_reference(y, F.linear(y, u.double()), 0.2)
    with torch.no_grad():
        got = fused.lin_act_mean(x, w, u, 0.2)
    assert got.dtype == torch.float32 and got.shape == (3, 11, 3, c)
    torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-4)
    with pytest.raises(RuntimeError, match="w must be"):
        torch.ops.efem_vn.lin_act_mean(x, w[:, :-1], u, 0.2)
    with pytest.raises(RuntimeError, match="u must be"):
        torch.ops.efem_vn.lin_act_mean(x, w, u[:-1], 0.2)


@needs_kernels
@pytest.mark.parametrize("seed", [0, 1])
def test_attention_kernel_matches_the_reference(seed: int) -> None:
    """The fused VN attention (values, keys, per-head softmax over the neighbours) against the eager reference,
    with a zero key (the norm's floor) and zero directions among the edges."""
    f_src, f_dst, nbr = _edge_inputs(seed, c=32)
    g = torch.Generator().manual_seed(seed)
    v = tuple(torch.randn(t.shape, generator=g) for t in (f_src, f_dst, f_src, f_dst))
    k = tuple(torch.randn(t.shape, generator=g) for t in (f_src, f_dst, f_src, f_dst))
    k[0][0].zero_()
    k[1][0, 0].zero_()  # point 0's keys from source 0 are zero vectors
    v[2][0, 1] = 0.0
    q = torch.randn(f_dst.shape, generator=g)
    q = q / q.flatten(-2).norm(dim=-1)[..., None, None]
    for head_dim in (8, 16, 32):
        ref = fused.attention_reference(v, k, q, nbr, 0.2, head_dim)
        got = torch.ops.efem_vn.attention(*v, *k, q, nbr, 0.2, head_dim, 1e-12)
        torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)
    bad = nbr.clone()
    bad[0, 0, 0] = f_src.shape[1]
    with pytest.raises(RuntimeError, match="out of range"):
        torch.ops.efem_vn.attention(*v, *k, q, bad, 0.2, 16, 1e-12)
    with pytest.raises(RuntimeError, match="multiple of head_dim"):
        torch.ops.efem_vn.attention(*v, *k, q, nbr, 0.2, 12, 1e-12)


@needs_kernels
def test_edge_kernel_refuses_bad_indices_and_shapes() -> None:
    f_src, f_dst, nbr = _edge_inputs(2)
    bad = nbr.clone()
    bad[0, 0, 0] = f_src.shape[1]  # one past the end: would read outside the tensor
    with pytest.raises(RuntimeError, match="out of range"):
        torch.ops.efem_vn.edge_mean(f_src, f_dst, f_src, f_dst, bad, 0.2)
    bad[0, 0, 0] = -1
    with pytest.raises(RuntimeError, match="out of range"):
        torch.ops.efem_vn.edge_mean(f_src, f_dst, f_src, f_dst, bad, 0.2)
    with pytest.raises(RuntimeError, match="float32"):
        torch.ops.efem_vn.edge_mean(f_src.double(), f_dst, f_src, f_dst, nbr, 0.2)
    with pytest.raises(RuntimeError, match="match"):
        torch.ops.efem_vn.edge_mean(f_src, f_dst, f_src[:, :5], f_dst, nbr, 0.2)


@needs_kernels
@pytest.mark.parametrize(("b", "nq", "nr", "dim", "k"), [(4, 64, 64, 3, 16), (3, 16, 64, 48, 16), (2, 40, 40, 96, 16),
                                                         (2, 7, 5, 4, 5), (2, 9, 2000, 3, 8), (1, 3, 11, 2, 1)])
def test_knn_selection_gives_the_eager_neighbours_index_for_index(b: int, nq: int, nr: int, dim: int, k: int) -> None:
    """`fused.knn` returns what `knn_indices` (the eager topk) returns, to the index and its place, where points
    are distinct, including equal distances between different points (coordinates on a coarse grid: many exact
    ties), a NaN row and both of torch's selection paths (k * 64 <= Nr and not). Among duplicate points (the
    M-step draws with replacement) it may pick another copy, never another value: what the indices gather equals
    what the eager ones gather, entry for entry, and the rows without duplicates keep the eager indices."""
    from efem_viz.geometry.knn import knn_indices

    g = torch.Generator().manual_seed(b * 1000 + nr)
    ref = torch.randn(b, nr, dim, generator=g)
    dup = ref.clone()
    dup[:, nr // 2] = dup[:, 0]  # duplicates
    dup[:, -1] = dup[:, 0]
    query = dup[:, :nq].clone() if nq <= nr else torch.randn(b, nq, dim, generator=g)
    grid = torch.unique(torch.round(torch.randn(b * nr * 4, dim, generator=g) * 2.0) / 2.0, dim=0)  # distinct
    if len(grid) >= b * nr:
        grid = grid[torch.randperm(len(grid), generator=g)[:b * nr]].reshape(b, nr, dim)  # ties everywhere
    else:  # too few distinct grid points for this size: a finer grid
        grid = torch.round(torch.randn(b, nr, dim, generator=g) * 64.0) / 64.0
    nan = dup.clone()
    nan[0, 1, 0] = float("nan")
    for q, r, distinct in ((query, dup, False), (torch.randn(b, nq, dim, generator=g), dup, False),
                           (torch.randn(b, nq, dim, generator=g), ref, True), (grid[:, :nq], grid, True),
                           (query, nan, False)):
        with torch.no_grad():
            want = knn_indices(q, r, k)
            got = fused.knn(q, r, k)
        assert got.dtype == torch.int64 and got.shape == (b, min(nq, q.shape[1]), k)
        rows = torch.arange(b)[:, None, None]
        assert torch.equal(r[rows, got].nan_to_num(7.0), r[rows, want].nan_to_num(7.0))
        if distinct:
            assert torch.equal(got, want)
        else:  # a row whose neighbours hold no copy of point 0 is decided as the eager one decides it
            copies = torch.zeros(nr, dtype=torch.bool)
            copies[[0, nr // 2, nr - 1]] = True
            clean = ~copies[want].any(-1) & ~copies[got].any(-1)
            assert torch.equal(got[clean], want[clean])


@needs_kernels
@pytest.mark.parametrize("threads", [1, 2])
def test_knn_by_gram_slabs_equals_the_selection_on_the_whole_gram_matrix(threads: int) -> None:
    """The slab kernel (Gram rows 64 query rows at a time) gives the indices of `knn_select` on the batched
    product, bit for bit, at slab edges (130 = 2 x 64 + 2 rows), with duplicates, a NaN and more queries than
    references, on one and two threads."""
    g = torch.Generator().manual_seed(11)
    old_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for b, nq, nr, dim in ((3, 130, 130, 48), (2, 200, 64, 3), (2, 64, 1024, 6), (1, 1, 17, 5)):
            r = torch.randn(b, nr, dim, generator=g)
            r[:, nr // 2] = r[:, 0]
            q = torch.cat([r[:, : min(nq, nr)], torch.randn(b, max(0, nq - nr), dim, generator=g)], 1)
            q[0, -1, 0] = float("nan")
            qq, rr = (q * q).sum(-1), (r * r).sum(-1)
            want = torch.ops.efem_vn.knn_select(q @ r.transpose(1, 2), qq, rr, min(16, nr), r)
            assert torch.equal(torch.ops.efem_vn.knn(q, r, qq, rr, min(16, nr)), want)
    finally:
        torch.set_num_threads(old_threads)
    with pytest.raises(RuntimeError, match="must be float32 and agree"):
        torch.ops.efem_vn.knn(q, r[..., :-1], qq, rr, 3)
    with pytest.raises(RuntimeError, match="rr must be"):
        torch.ops.efem_vn.knn(q, r, qq, rr[:, :-1], 3)
    with pytest.raises(RuntimeError, match=r"k must be in \[1, Nr\]"):
        torch.ops.efem_vn.knn(q, r, qq, rr, nr + 1)


@needs_kernels
def test_knn_of_bf16_features_runs_the_selection_in_float32(monkeypatch: pytest.MonkeyPatch) -> None:
    """A bf16 autocast's features (training) take the one-pass selection on their float32 values, with the
    neighbours the eager function finds for them, not `topk` over a bf16 distance matrix."""
    from efem_viz.geometry.knn import knn_indices

    g = torch.Generator().manual_seed(5)
    ref = torch.randn(3, 96, 48, generator=g).bfloat16()
    query = ref[:, :40].clone()
    calls = []
    select = torch.ops.efem_vn.knn
    monkeypatch.setattr(fused.torch.ops.efem_vn, "knn", lambda *a: calls.append(a[0].dtype) or select(*a),
                        raising=False)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = fused.knn(query, ref, 16)
    assert calls == [torch.float32]
    assert torch.equal(got, knn_indices(query, ref, 16))


@needs_kernels
def test_knn_selection_refuses_bad_shapes_and_k() -> None:
    gram, qq, rr = torch.randn(2, 5, 7), torch.randn(2, 5), torch.randn(2, 7)
    with pytest.raises(RuntimeError, match=r"k must be in \[1, Nr\]"):
        torch.ops.efem_vn.knn_select(gram, qq, rr, 8)
    with pytest.raises(RuntimeError, match="rr must be"):
        torch.ops.efem_vn.knn_select(gram, qq, rr[:, :6], 3)
    with pytest.raises(RuntimeError, match="float32"):
        torch.ops.efem_vn.knn_select(gram.double(), qq, rr, 3)
    with pytest.raises(ValueError, match="k must be in"):  # the Python entry gives the eager function's message
        fused.knn(torch.randn(2, 5, 3), torch.randn(2, 7, 3), 0)


def test_kernels_leave_autograd_float64_and_a_switched_off_process_to_the_references(
        monkeypatch: pytest.MonkeyPatch) -> None:
    x = torch.randn(2, 4, 3, 8, requires_grad=True)
    assert not fused.usable(x)  # training: gradients flow through the eager ops
    with torch.no_grad():
        assert not fused.usable(x.double())
        monkeypatch.setenv("EFEM_VIZ_FUSED", "0")
        assert not fused.usable(x)


ENCODERS = {
    "mean": dict(widths=(8, 8, 16, 16, 32), down_blocks=(2, 4), down_factors=(2, 4), k=8, n_pcl=128),
    # the chair design: VN attention in blocks 2-4
    "attention": dict(widths=(16, 16, 32, 32, 32), down_blocks=(2, 4), down_factors=(4, 4), k=8, n_pcl=256,
                      attention_blocks=(2, 3, 4), att_head_dim=16),
}


def _grads(fn, inputs: list[torch.Tensor], dtype: torch.dtype, seed: int = 5) -> list[torch.Tensor]:
    """The output and the input gradients of ``sum(fn(*inputs) * G)`` for a fixed random G, in float64."""
    leaves = [t.to(dtype).detach().requires_grad_() for t in inputs]
    out = fn(*leaves)
    weight = torch.randn(out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    (out.double() * weight).sum().backward()
    return [out.detach().double()] + [t.grad.double() for t in leaves]  # type: ignore[union-attr]


def _edge_terms(seed: int, b: int = 3, ns: int = 40, nd: int = 30, k: int = 8, c: int = 16
                ) -> tuple[list[torch.Tensor], torch.Tensor]:
    """a, c, da, dc in float64 with duplicate neighbours (a source named twice by one destination) and edges at the
    activation's bounds: a zero direction (|d|^2 below the clamp) and x ⟂ d (dot = 0)."""
    g = torch.Generator().manual_seed(seed)
    a, dst = torch.randn(b, ns, 3, c, generator=g, dtype=torch.float64), torch.randn(b, nd, 3, c, generator=g,
                                                                                      dtype=torch.float64)
    da, dc = torch.randn(b, ns, 3, c, generator=g, dtype=torch.float64), torch.randn(b, nd, 3, c, generator=g,
                                                                                      dtype=torch.float64)
    nbr = torch.randint(0, ns, (b, nd, k), generator=g)
    nbr[:, :, 1] = nbr[:, :, 0]
    da[0, nbr[0, 0, 2]], dc[0, 0] = 0.0, 0.0  # a zero direction on one edge
    return [a, dst, da, dc], nbr


@needs_kernels
@pytest.mark.parametrize("seed", [0, 1])
def test_training_kernels_give_the_eager_gradients(seed: int) -> None:
    """In training (autograd on, float32) the edge mean, every edge's activation and the activation itself run fused
    forward and backward; outputs and gradients equal the eager float64 graph's to float32 rounding."""
    terms, nbr = _edge_terms(seed)
    cases = [
        (lambda *t: fused.edge_mean_reference(*t, nbr, 0.2),
         lambda *t: fused._Edges.apply(*t, nbr, 0.2, True), terms),
        (lambda *t: fused._edge_act_reference(*t, nbr, 0.2), lambda *t: fused._edge_act_trained(*t, nbr, 0.2), terms),
        (lambda x, d: fused.vn_leaky_relu(x, d, 0.2), lambda x, d: fused.leaky(x, d, 0.2), [terms[0], terms[2]]),
    ]
    for ref_fn, fused_fn, inputs in cases:
        ref = _grads(ref_fn, inputs, torch.float64)
        got = _grads(fused_fn, inputs, torch.float32)
        for r, x in zip(ref, got):
            assert torch.isfinite(x).all()
            assert float((r - x).abs().max() / r.abs().max()) < 2e-6
    # the public entries take the fused path in training and the eager one in float64
    x, d = terms[0].float().requires_grad_(), terms[2].float()
    assert fused.trainable(x, d) and not fused.trainable(x.double(), d.double())
    with torch.no_grad():
        assert not fused.trainable(x, d)  # inference: `usable` decides, the eager roundings stay


@needs_kernels
def test_training_kernels_take_bf16_autocast_inputs_and_sum_in_a_fixed_order() -> None:
    """bf16 inputs (an autocast's products) are computed in float32; the backward's sums over destinations run in
    one order, so one and two threads give the same bits."""
    terms, nbr = _edge_terms(3)
    x32 = [t.float() for t in terms]
    out = fused._edge_act_trained(*[t.bfloat16().requires_grad_() for t in x32], nbr, 0.2)
    assert out.dtype == torch.float32
    ref = fused._edge_act_reference(*[t.bfloat16().float() for t in x32], nbr, 0.2)
    torch.testing.assert_close(out.detach(), ref, rtol=1e-5, atol=1e-5)
    grad = torch.randn(out.shape, generator=torch.Generator().manual_seed(0))
    threads = torch.get_num_threads()
    try:
        got = []
        for n in (1, 2):
            torch.set_num_threads(n)
            got.append(torch.ops.efem_vn.edge_act_backward(grad, *x32, nbr, 0.2))
    finally:
        torch.set_num_threads(threads)
    for u, v in zip(*got):
        assert torch.equal(u, v)


@needs_kernels
def test_training_kernels_refuse_bad_indices_and_shapes() -> None:
    terms, nbr = _edge_terms(4)
    x32 = [t.float() for t in terms]
    bad = nbr.clone()
    bad[0, 0, 0] = 10**6
    with pytest.raises(RuntimeError, match="out of range"):
        torch.ops.efem_vn.edge_act(*x32, bad, 0.2)
    with pytest.raises(RuntimeError, match="out of range"):
        torch.ops.efem_vn.edge_mean_backward(torch.zeros_like(x32[1]), *x32, bad, 0.2)
    with pytest.raises(RuntimeError, match="grad must"):
        torch.ops.efem_vn.edge_act_backward(torch.zeros(1), *x32, nbr, 0.2)
    with pytest.raises(RuntimeError, match="d must match"):
        torch.ops.efem_vn.leaky(x32[0], x32[1], 0.2)


@needs_kernels
@pytest.mark.parametrize("design", sorted(ENCODERS))
def test_training_encoder_gradients_with_kernels_match_the_eager_graph(design: str,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A training step's encoder gradients (mean aggregation and the chair design's attention) with the kernels:
    the eager float64 graph's to float32 rounding, as close as the eager float32 graph gets."""
    torch.manual_seed(0)
    cfg = ENCODERS[design]
    prior = ShapePrior(PriorConfig(**cfg, latent_dim=16, center_hidden=8, decoder_hidden=32,  # type: ignore[arg-type]
                                   decoder_blocks=2))
    pts = torch.randn(2, int(cfg["n_pcl"]), 3) * 0.2  # type: ignore[call-overload]

    def grads(dtype: torch.dtype, kernels: bool) -> torch.Tensor:
        monkeypatch.setenv("EFEM_VIZ_FUSED", "1" if kernels else "0")
        enc = prior.encoder.to(dtype)
        enc.zero_grad()
        out = enc(pts.to(dtype))
        (out.R.double().square().sum() + out.inv.double().sum() + out.delta.double().sum()).backward()
        return torch.cat([q.grad.double().reshape(-1) for q in enc.parameters() if q.grad is not None])

    ref = grads(torch.float64, False)
    eager = grads(torch.float32, False)
    fast = grads(torch.float32, True)
    scale = float(ref.abs().max())
    assert float((fast - ref).abs().max()) / scale < max(4 * float((eager - ref).abs().max()) / scale, 1e-5)


@needs_kernels
@pytest.mark.parametrize("design", sorted(ENCODERS))
def test_encoder_with_kernels_matches_the_eager_encoder(design: str, monkeypatch: pytest.MonkeyPatch) -> None:
    torch.manual_seed(0)
    cfg = ENCODERS[design]
    prior = ShapePrior(PriorConfig(**cfg, latent_dim=16, center_hidden=8, decoder_hidden=32,  # type: ignore[arg-type]
                                   decoder_blocks=2)).eval()
    pts = torch.randn(3, int(cfg["n_pcl"]), 3) * 0.2  # type: ignore[call-overload]
    with torch.no_grad():
        fast = prior.encode(pts)
        monkeypatch.setenv("EFEM_VIZ_FUSED", "0")
        slow = prior.encode(pts)
    for name in ("R", "inv", "center", "scale"):
        torch.testing.assert_close(getattr(fast, name), getattr(slow, name), rtol=1e-4, atol=1e-5)


def test_a_killed_first_build_is_rebuilt_and_a_concurrent_one_means_eager_not_a_wait(tmp_path) -> None:
    """A first build killed part-way used to leave torch's `lock` file behind, and every later run waited for it
    forever. Full processes, a private cache folder: a build killed after a few seconds, then a process that builds
    and loads the kernels (the stale lock removed, within a hang guard far above a build); while one process
    builds, another starts: it runs eagerly at once, with one line saying why, and waits for nothing."""
    import os
    import subprocess
    import sys
    import time

    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "EFEM_VIZ_FUSED": "1"}
    code = ("import logging, sys; logging.basicConfig(level=logging.INFO, stream=sys.stdout); "
            "from efem_viz.prior import fused; print('LOADED', fused.load(), flush=True)")
    first = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True)
    folder = tmp_path / "cache" / "efem-viz" / "torch_extensions"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and not list(folder.glob("efem_vn_*/lock")):  # torch's build lock appears
        time.sleep(0.2)
    assert list(folder.glob("efem_vn_*/lock")), "the build never started"
    busy = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert "LOADED False" in busy.stdout and "another process is building" in busy.stdout, busy.stdout
    first.kill()
    first.wait(60)
    assert list(folder.glob("efem_vn_*/lock")), "the killed build left its lock (the case under test)"
    again = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=1800)
    assert "LOADED True" in again.stdout and "interrupted build" in again.stdout, again.stdout + again.stderr
    warm = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert "LOADED True" in warm.stdout and "building" not in warm.stdout  # a valid build is never rebuilt


def test_a_pending_build_is_told_before_it_starts_and_a_finished_one_is_not(tmp_path, monkeypatch: pytest.MonkeyPatch
                                                                            ) -> None:
    """`prepare` tells its caller when `load` will compile (no finished build of this key on disk), and only
    then; a process that has decided (loaded, or fell back) never asks again."""
    monkeypatch.setattr(fused, "_build_dir", lambda: tmp_path)
    monkeypatch.setattr(fused, "_state", {"loaded": None})
    monkeypatch.setattr(fused, "load", lambda: True)
    said: list[str] = []
    assert fused.pending_build()
    fused.prepare(said.append)
    assert said == [fused.BUILD_NOTICE]
    name = f"efem_vn_{fused.build_key(fused.SOURCE.read_text(encoding='utf-8'), fused._flags())}"
    (tmp_path / name).mkdir()
    (tmp_path / name / f"{name}.so").write_bytes(b"")
    assert not fused.pending_build()
    fused.prepare(said.append)
    assert said == [fused.BUILD_NOTICE]
    (tmp_path / name / f"{name}.so").unlink()
    monkeypatch.setattr(fused, "_state", {"loaded": False})
    assert not fused.pending_build()


def _decoder(hidden: int, blocks: int, use_qnorm: bool, seed: int) -> SDFDecoder:
    from efem_viz.prior.decoder import SDFDecoder

    torch.manual_seed(seed)
    dec = SDFDecoder(latent_dim=6, hidden=hidden, n_blocks=blocks, use_qnorm=use_qnorm).eval()
    with torch.no_grad():
        for p in dec.parameters():  # fc_1 starts at zero: give every block something to do
            p.copy_(torch.randn_like(p) / p.shape[-1] ** 0.5)
    return dec


def _decoder_inputs(dec: SDFDecoder, b: int, n: int, seed: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    m, bias = dec.fold(torch.randn(b, 6, 3, generator=g), torch.randn(b, 6, generator=g))
    return torch.randn(b, n, 3, generator=g), m.detach(), bias.detach()


@needs_kernels
@pytest.mark.parametrize("hidden,blocks,use_qnorm,b,n", [(32, 2, True, 3, 301), (16, 1, False, 5, 97),
                                                          (24, 3, True, 1, 1000)])
def test_fused_decoder_pass_matches_the_eager_tiles(hidden: int, blocks: int, use_qnorm: bool, b: int, n: int,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """SDF of every query, the band and ∂sdf/∂q of the band rows as the eager tiles give them (float32 rounding),
    for row counts that are no multiple of the tile, with and without the ‖q‖ feature."""
    dec = _decoder(hidden, blocks, use_qnorm, seed=hidden)
    q, m, bias = _decoder_inputs(dec, b, n, seed=blocks)
    with torch.no_grad():
        monkeypatch.setenv("EFEM_VIZ_FUSED_DECODER", "0")
        ref_fwd = dec.forward_batched(q, m, bias)
        levels = ref_fwd.abs().flatten().sort().values
        within = float(levels[len(levels) // 2] + levels[len(levels) // 2 + 1]) / 2  # half the rows, no tie
        ref = dec.sdf_and_band_grad(q, m, bias, within=within)
        monkeypatch.setenv("EFEM_VIZ_FUSED_DECODER", "1")
        calls = []
        plain = fused.decoder_band
        monkeypatch.setattr(fused, "decoder_band", lambda *a, **k: calls.append(1) or plain(*a, **k))
        fwd = dec.forward_batched(q, m, bias)
        out = dec.sdf_and_band_grad(q, m, bias, within=within)
    assert len(calls) == 2  # both inference passes took the kernel
    torch.testing.assert_close(fwd, ref_fwd, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out[0], ref[0], rtol=1e-5, atol=1e-5)
    assert torch.equal(out[2], ref[2]) and 0 < int(out[2].sum()) < b * n
    torch.testing.assert_close(out[1], ref[1], rtol=1e-4, atol=1e-5)
    assert torch.all(out[1][~out[2]] == 0)


def _bf16_products_reference(dec: SDFDecoder, q: torch.Tensor, m: torch.Tensor, bias: torch.Tensor, within: float
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eager `sdf_and_band_grad` with the hidden products' operands rounded to bf16 (float32 products: a
    product of two bf16 values is exact in float64 and float32 alike) and everything else float32: what the
    kernel's bf16 pass computes."""
    def bmm(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return (x.bfloat16().double() @ w.bfloat16().double()).float()

    relu = torch.relu
    hs, us = [dec._first_layer(q, m, bias)], []
    for i in range(dec.n_blocks):
        blk = getattr(dec, f"block{i}")
        us.append(bmm(relu(hs[-1]), blk.fc_0.weight.t()) + blk.fc_0.bias)
        hs.append(hs[-1] + bmm(relu(us[-1]), blk.fc_1.weight.t()) + blk.fc_1.bias)
    sdf = relu(hs[-1]) @ dec.fc_out.weight[0] + dec.fc_out.bias[0]
    band = sdf.abs() <= within
    g = (hs[-1] > 0).float() * dec.fc_out.weight[0]
    for i in reversed(range(dec.n_blocks)):
        blk = getattr(dec, f"block{i}")
        t = torch.where(us[i] > 0, bmm(g, blk.fc_1.weight), 0.0)
        g = g + (hs[i] > 0).float() * bmm(t, blk.fc_0.weight)
    q_req = q.clone().requires_grad_(True)
    with torch.enable_grad():  # d h0/dq contracted with g: the first layer's own (float32) gradient
        (dq,) = torch.autograd.grad((dec._first_layer(q_req, m, bias) * g).sum(), q_req)
    return sdf, torch.where(band[..., None], dq, 0.0), band


@needs_kernels
@pytest.mark.parametrize("onednn", [True, False], ids=["onednn", "blas"])
@pytest.mark.parametrize("hidden,blocks", [(40, 2), (32, 1), (128, 2)])
def test_fused_decoder_bf16_products_are_the_autocast_rounding(hidden: int, blocks: int, onednn: bool,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Under a CPU bf16 autocast the kernel rounds the hidden products' operands to bf16 (float32 products) and
    keeps the rest in float32: it matches an eager reference of that rounding far more closely than it matches
    float32, for widths with and without a partial vector (40 = 2 x 16 + 8; 32 and 128 take the bf16
    micro-kernel where the CPU has one), and the first-layer weights stay float32."""
    dec = _decoder(hidden, blocks, True, seed=hidden + blocks)
    g = torch.Generator().manual_seed(7)
    monkeypatch.setattr(torch.backends.mkldnn, "enabled", onednn)  # off: the BLAS GEMM path
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        m, bias = dec.fold(torch.randn(3, 6, 3, generator=g), torch.randn(3, 6, generator=g))
        q = torch.randn(3, 700, 3, generator=g)
        assert m.dtype == bias.dtype == torch.float32
        out = dec.sdf_and_band_grad(q, m, bias, within=0.5)
    with torch.no_grad():
        ref = _bf16_products_reference(dec, q, m, bias, 0.5)
        f32 = dec.sdf_and_band_grad(q, m, bias, within=0.5)
    assert 0 < int(ref[2].sum()) < ref[2].numel()
    same = out[2] & ref[2]
    assert same.float().mean() > 0.99 * ref[2].float().mean()
    # another float32 summation order can move an activation across a bf16 rounding boundary (one bf16 step,
    # 0.4 % of that unit) for a rare query: the bulk matches to float32 rounding, no query is far off
    d_sdf, d_dq = (out[0] - ref[0]).abs().flatten(), (out[1] - ref[1])[same].abs().flatten()
    gap_sdf, gap_dq = (f32[0] - ref[0]).abs().max(), (f32[1] - ref[1])[same].abs().max()
    assert gap_sdf > 1e-4 and d_sdf.quantile(0.99) < 0.001 * gap_sdf and d_sdf.max() < 0.05 * gap_sdf
    assert gap_dq > 1e-4 and d_dq.quantile(0.99) < 0.001 * gap_dq and d_dq.max() < 0.05 * gap_dq
    assert torch.all(out[1][~out[2]] == 0)


@needs_kernels
def test_fused_decoder_tiles_and_threads_change_nothing_but_rounding(monkeypatch: pytest.MonkeyPatch) -> None:
    dec = _decoder(32, 2, True, seed=3)
    q, m, bias = _decoder_inputs(dec, 4, 250, seed=4)
    threads = torch.get_num_threads()
    with torch.no_grad():
        one = dec.sdf_and_band_grad(q, m, bias, within=0.5)
        monkeypatch.setattr(fused, "DECODER_TILE", 7)  # 143 tiles, the last one of 6 rows
        try:
            torch.set_num_threads(2)
            small = dec.sdf_and_band_grad(q, m, bias, within=0.5)
        finally:
            torch.set_num_threads(threads)
    for a, b in zip(one, small):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


@needs_kernels
@pytest.mark.parametrize("onednn", [True, False], ids=["onednn", "blas"])
def test_fused_decoder_bf16_pass_is_the_same_in_any_tiles_and_threads(monkeypatch: pytest.MonkeyPatch,
                                                                      onednn: bool) -> None:
    """The bf16 pass in 7-row tiles on two threads gives what the default tiles on one thread give, to float32
    rounding (the same bits on the packed micro-kernel of an AMX CPU; a BLAS GEMM may round by its row count),
    at a width that takes the micro-kernel where the CPU has one, and with oneDNN off (the BLAS GEMM path)."""
    dec = _decoder(128, 2, True, seed=5)
    g = torch.Generator().manual_seed(6)
    threads = torch.get_num_threads()
    monkeypatch.setattr(torch.backends.mkldnn, "enabled", onednn)  # off: the BLAS GEMM path
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        m, bias = dec.fold(torch.randn(3, 6, 3, generator=g), torch.randn(3, 6, generator=g))
        q = torch.randn(3, 900, 3, generator=g)
        try:
            torch.set_num_threads(1)
            one = dec.sdf_and_band_grad(q, m, bias, within=0.5)
            monkeypatch.setattr(fused, "DECODER_TILE_BF16", 7)
            monkeypatch.setattr(fused, "DECODER_TILE_BF16_AMX", 7)
            torch.set_num_threads(2)
            small = dec.sdf_and_band_grad(q, m, bias, within=0.5)
        finally:
            torch.set_num_threads(threads)
    assert 0 < int(one[2].sum()) < one[2].numel()
    # a GEMM that rounds by its row count can move an activation across a bf16 rounding boundary for a rare query
    # (one bf16 step of that unit); the bulk must agree to float32 rounding and no query be far off
    assert (one[2] == small[2]).float().mean() > 0.999
    for a, b in zip(one, small):
        d = (a.float() - b.float()).abs()
        assert (d <= 1e-5 * (1.0 + a.float().abs())).float().mean() > 0.995 and float(d.max()) < 1e-2


@needs_kernels
def test_fused_decoder_leaves_training_float64_and_bad_shapes_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    dec = _decoder(16, 2, True, seed=5)
    q, m, bias = _decoder_inputs(dec, 2, 100, seed=6)
    monkeypatch.setattr(fused, "decoder_band", lambda *a, **k: pytest.fail("the kernel must not serve this call"))
    q.requires_grad_(True)
    sdf = dec.forward_batched(q, m, bias)  # training: autograd through the eager ops
    (grad,) = torch.autograd.grad(sdf.sum(), q)
    assert grad.abs().sum() > 0
    with torch.no_grad():
        dec64 = _decoder(16, 2, True, seed=5).double()
        dec64.forward_batched(q.detach().double(), m.double(), bias.double())
        monkeypatch.setenv("EFEM_VIZ_FUSED_DECODER", "0")
        dec.forward_batched(q.detach(), m, bias)
    w = torch.zeros(16, 16)
    with pytest.raises(RuntimeError, match="mt must be"):
        torch.ops.efem_vn.decoder_band(q.detach(), torch.zeros(2, 4, 16), [w], [torch.zeros(16)], [w],
                                       [torch.zeros(16)], torch.zeros(16), 0.0, 0.1, True, 8)
    with pytest.raises(RuntimeError, match="block weights"):
        torch.ops.efem_vn.decoder_band(q.detach(), torch.zeros(2, 5, 16), [torch.zeros(16, 8)], [torch.zeros(16)],
                                       [w], [torch.zeros(16)], torch.zeros(16), 0.0, 0.1, True, 8)


@needs_kernels
@pytest.mark.parametrize(("b", "n", "dim", "m", "start"), [(200, 256, 3, 64, 0), (4, 128, 3, 32, 5), (2, 9, 1, 9, 8),
                                                           (3, 50, 48, 12, 0), (1, 1, 3, 1, 0)])
def test_fps_gives_the_eager_indices(b: int, n: int, dim: int, m: int, start: int) -> None:
    """`fused.fps` returns `farthest_point_sample`'s indices, index for index: random points, duplicate points
    (the M-step draws with replacement: equal distances everywhere), coordinates on a coarse grid (equal maxima:
    the first one wins in both), and non-finite points (the eager loop decides)."""
    from efem_viz.geometry.fps import farthest_point_sample

    g = torch.Generator().manual_seed(b * 100 + n)
    pts = torch.randn(b, n, dim, generator=g)
    dup = pts[:, torch.randint(0, max(1, n // 2), (n,), generator=g)]
    grid = torch.round(torch.randn(b, n, dim, generator=g) * 2.0) / 2.0
    turned = grid @ torch.linalg.qr(torch.randn(b, dim, dim, generator=g))[0]  # maxima equal but for rounding
    bad = pts.clone()
    bad[0, n // 2, 0] = float("nan")
    for x in (pts, dup, grid, turned, pts * 1e3, bad):
        want = farthest_point_sample(x, m, start=start)
        got = fused.fps(x, m, start=start)
        assert got.dtype == torch.int64 and torch.equal(got, want)
    with pytest.raises(ValueError, match="n_samples"):
        fused.fps(pts, n + 1)
