"""Fused CPU kernels: the encoder's VN edge passes (one pass over the edges instead of fifteen) and the decoder's
inference pass.

The VN-DGCNN encoder spends most of its time not in matrix products but in the VN-LeakyReLU applied to every
edge feature ``(B, N, k, 3, C)`` and the mean over the ``k`` neighbours that follows: a dozen elementwise passes
over a ``k``-fold tensor, memory-bound. Two exact rewrites remove that:

1. the activation's directions are linear in the edge feature (``d = U x``) and the edge feature is
   ``x = a[nbr] + c``, so ``d = (U a)[nbr] + U c``: the direction GEMM runs once per point, not once per edge;
2. `edge_mean` / `act_mean` gather, activate and average in one loop per point (``vn_kernels.cpp``), never
   writing the ``k``-fold tensors (45x faster than the eager ops at the shipped widths, one thread).

The k-NN of every block (in feature space) keeps the eager Gram product and replaces the `topk` over the
distance matrix by one selection pass per row (`knn`: the same neighbours in the same order; among copies of one
point, another copy may stand for it, never another value). The first layer's two products, activation and mean
run in one pass per point (`lin_act_mean`), and the down-sampling's farthest-point sampling in one loop per point
set (`fps`, the same indices as the eager loop).

The decoder's inference pass (`decoder_band`, serving `SDFDecoder.forward_batched` and `sdf_and_band_grad`) runs
in one C++ loop over tiles of 256 rows: the first layer, each block's two products with bias, ReLU and residual
fused into the pass that follows each product, the output, and the band rows' input gradient, every activation
of a tile kept in cache (float32, the eager tiles' result to rounding; ``EFEM_VIZ_FUSED_DECODER=0`` turns this
one off). Under a CPU bf16 autocast (`EMConfig.compute.matmul_dtype` "bfloat16") its hidden products take bf16
operands and give float32 results (torch's CPU BLAS: the packed bf16 micro-kernel where the CPU has AMX, its bf16
GEMM with float32 results elsewhere), while the first layer, the residual stream, the output and the gradient's
sums stay float32 (closer to float32 than the eager bf16 tiles, whose whole stream is bf16), in tiles of
`bf16_tile()` rows.

The C++ file is compiled on first use with torch's own toolchain support (`torch.utils.cpp_extension`, about
35 s once per machine, cached under ``~/.cache/efem-viz/torch_extensions`` in a folder keyed by everything that
changes the build, `build_key`; an exclusive flock makes a build safe against concurrent and killed ones). The eager
references below are the same math and serve everything the kernels do not: float64 (the equivariance tests),
autograd (training), autocast (but the decoder's CPU bf16), CUDA, and any machine where the build
fails (one warning, then eager for the rest of the process). ``EFEM_VIZ_FUSED=0`` turns the kernels off.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from pathlib import Path
from typing import Any, Callable

import torch
import torch.nn.functional as F

from efem_viz.prior.vn_math import EPS, vn_leaky_relu

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("vn_kernels.cpp")

_lock = threading.Lock()
_state: dict[str, Any] = {"loaded": None}  # None: not tried; True: ops registered; False: unavailable


def edge_mean_reference(a: torch.Tensor, c: torch.Tensor, da: torch.Tensor, dc: torch.Tensor, nbr: torch.Tensor,
                        slope: float) -> torch.Tensor:
    """Eager ``mean_k act(x, d)`` with ``x = a[nbr] + c`` and its directions ``d = da[nbr] + dc``.

    Args:
        a: ``(B, Ns, 3, C)`` per-source-point term ``W1 f_j``.
        c: ``(B, Nd, 3, C)`` per-destination term ``(W2 − W1) f_i``.
        da: ``(B, Ns, 3, C)`` ``U a`` (``U`` the activation's direction weights).
        dc: ``(B, Nd, 3, C)`` ``U c``.
        nbr: ``(B, Nd, k)`` int64 indices into ``Ns``.
        slope: negative slope α.

    Returns:
        ``(B, Nd, 3, C)``.
    """
    b = a.shape[0]
    ar = torch.arange(b, device=a.device).view(b, 1, 1)
    x = a[ar, nbr] + c[:, :, None]
    d = da[ar, nbr] + dc[:, :, None]
    return vn_leaky_relu(x, d, slope).mean(dim=2)


def act_mean_reference(x: torch.Tensor, d: torch.Tensor, slope: float) -> torch.Tensor:
    """Eager ``mean_k act(x, d)`` for ``x, d (B, Nd, k, 3, C)``; returns ``(B, Nd, 3, C)``."""
    return vn_leaky_relu(x, d, slope).mean(dim=2)


def _build_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "efem-viz" / "torch_extensions"


def _flags() -> list[str]:
    """Vector flags for the CPU torch itself dispatches to (never -march=native: a cache may move)."""
    cap = torch.backends.cpu.get_cpu_capability()
    if cap.startswith("AVX512"):
        return ["-mavx512f", "-mavx2", "-mfma"]
    if cap == "AVX2":
        return ["-mavx2", "-mfma"]
    return []


def build_key(src: str, flags: list[str]) -> str:
    """Hash of everything that changes the compiled file: the source, torch, Python, the compiler and its
    version, the flags and torch's include paths. Environments that differ in any of them build into their own
    folder; equal ones share one build and never rebuild it."""
    import hashlib
    import platform
    import subprocess
    import sys

    cxx = os.environ.get("CXX", "c++")
    try:
        out = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30)
        version = (out.stdout.splitlines() or ["?"])[0]
    except (OSError, subprocess.SubprocessError):
        version = "unavailable"
    try:
        from torch.utils.cpp_extension import include_paths

        includes = [str(p) for p in include_paths()]
    except Exception:  # noqa: BLE001 - a torch without cpp_extension: the build fails later, with its reason
        includes = []
    parts = [src, torch.__version__, sys.version, platform.machine(), cxx, version, *flags, *includes]
    return hashlib.sha1("\n".join(parts).encode()).hexdigest()[:12]


def load() -> bool:
    """Build (first time) and register the kernels; False where they are unavailable (the reason is logged).

    A finished build is loaded as it is (never rebuilt). A build runs under an exclusive `flock` of the build
    folder, which the system releases when its process dies, so a lock file left by a killed build is known to
    be stale and removed. While another live process builds, this one does not wait: it runs the eager encoder
    (the same math) and says so in one line.
    """
    if _state["loaded"] is not None:  # decided: no lock on the encoder's hot path
        return bool(_state["loaded"])
    with _lock:
        if _state["loaded"] is None:
            _state["loaded"] = False
            if os.environ.get("EFEM_VIZ_FUSED", "1") == "0":
                return False
            try:
                _state["loaded"] = _load_or_build()
            except Exception as exc:  # noqa: BLE001 - no compiler, no headers, ...: keep working, eagerly
                msg = str(exc).strip().splitlines()
                log.warning("fused VN kernels unavailable (%s: %s); the encoder runs eagerly (slower)",
                            type(exc).__name__, msg[-1][:200] if msg else "")
        return bool(_state["loaded"])


BUILD_NOTICE = "building the fused VN kernels (once per machine, about 35 s) …"
"""What an app shows while a first run on a machine compiles the kernels (`prepare`)."""


def pending_build() -> bool:
    """Whether the next `load` compiles the kernels: not decided in this process yet, not turned off, and no
    finished build of this source, compiler and torch on disk."""
    if _state["loaded"] is not None or os.environ.get("EFEM_VIZ_FUSED", "1") == "0":
        return False
    try:
        _, _, lib = _library()
    except Exception:  # noqa: BLE001 - whatever stops the key stops the build too; `load` says why
        return False
    return not lib.is_file()


def prepare(say: Callable[[str], None] | None = None) -> bool:
    """`load`, telling `say` first when that compiles the kernels (a first run on a machine, which otherwise
    shows no step for the half minute the compiler takes). Returns what `load` returns."""
    if say is not None and pending_build():
        say(BUILD_NOTICE)
    return load()


def _registered() -> bool:
    return all(hasattr(torch.ops.efem_vn, op) for op in ("edge_mean", "act_mean", "attention", "decoder_band", "knn"))


def _library() -> tuple[str, list[str], Path]:
    """(source, compiler flags, path of the built library) of this source, compiler and torch."""
    src = SOURCE.read_text(encoding="utf-8")
    flags = _flags()
    name = f"efem_vn_{build_key(src, flags)}"
    return src, flags, _build_dir() / name / f"{name}.so"


def _load_or_build() -> bool:
    import fcntl

    src, flags, lib = _library()
    build, name = lib.parent, lib.stem
    build.mkdir(parents=True, exist_ok=True)
    if lib.is_file():
        try:
            torch.ops.load_library(str(lib))
            return _registered()
        except (OSError, RuntimeError) as exc:  # a build killed while linking: build it again below
            log.info("fused VN kernels at %s do not load (%s): building them again", lib, str(exc)[:120])
    with open(build / ".efem-build.lock", "a+") as held:
        try:
            fcntl.flock(held.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.warning("another process is building the fused VN kernels in %s; this one runs the eager "
                        "encoder (the same math, slower)", build)
            return False
        stale = build / "lock"  # torch's own build lock: only a flock holder builds, so a leftover is stale
        if stale.exists():
            log.info("removing the lock file of an interrupted build (%s)", stale)
            stale.unlink()
        if lib.is_file():  # built by the process that held the lock before us
            torch.ops.load_library(str(lib))
            return _registered()
        from torch.utils.cpp_extension import load_inline

        log.info("%s in %s", BUILD_NOTICE.rstrip(" …"), build)
        load_inline(name=name, cpp_sources=[src], is_python_module=False,
                    extra_cflags=["-O3", "-fopenmp", *flags], extra_ldflags=["-fopenmp"],
                    build_directory=str(build), verbose=False)
    return _registered()


def usable(*tensors: torch.Tensor, autocast_ok: bool = False) -> bool:
    """Whether the kernels serve a call on these tensors: float32 on the CPU, no autograd, no autocast (unless
    `autocast_ok`: a kernel that does the autocast's bf16 products itself, `decoder_band`)."""
    if os.environ.get("EFEM_VIZ_FUSED", "1") == "0" or _state["loaded"] is False:
        return False
    if torch.is_autocast_enabled("cpu") and not autocast_ok:
        return False
    for t in tensors:
        if t.dtype != torch.float32 or t.device.type != "cpu" or (torch.is_grad_enabled() and t.requires_grad):
            return False
    return load()


def trainable(*tensors: torch.Tensor) -> bool:
    """Whether the kernels with a fused backward serve a training call on these tensors: CPU, float32 or bfloat16
    (an autocast's products; the kernel computes in float32), autograd on for at least one of them. Float64 (the
    equivariance tests) keeps the eager references. ``EFEM_VIZ_FUSED_TRAINING=0`` (or ``EFEM_VIZ_FUSED=0``) turns
    them off."""
    if (os.environ.get("EFEM_VIZ_FUSED", "1") == "0" or os.environ.get("EFEM_VIZ_FUSED_TRAINING", "1") == "0"
            or _state["loaded"] is False or not torch.is_grad_enabled()):
        return False
    if not any(t.requires_grad for t in tensors):
        return False
    if any(t.dtype not in (torch.float32, torch.bfloat16) or t.device.type != "cpu" for t in tensors):
        return False
    return load() and hasattr(torch.ops.efem_vn, "leaky_backward")


class _Edges(torch.autograd.Function):
    """The edge kernels in training: ``VN-LeakyReLU(a[nbr] + c; da[nbr] + dc)`` averaged over each destination's
    edges (`edge_mean`) or of every edge ((B, Nd, k, 3, C), `edge_act`, the attention's), with a fused backward
    (`edge_mean_backward`, `edge_act_backward`) instead of the eager graph's k-fold gathers and scatter-adds."""

    @staticmethod
    def forward(ctx: Any, a: torch.Tensor, c: torch.Tensor, da: torch.Tensor, dc: torch.Tensor, nbr: torch.Tensor,
                slope: float, mean: bool) -> torch.Tensor:
        ctx.save_for_backward(a, c, da, dc, nbr)
        ctx.slope, ctx.mean = slope, mean
        op = torch.ops.efem_vn.edge_mean if mean else torch.ops.efem_vn.edge_act
        return op(a, c, da, dc, nbr, slope)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        a, c, da, dc, nbr = ctx.saved_tensors
        op = torch.ops.efem_vn.edge_mean_backward if ctx.mean else torch.ops.efem_vn.edge_act_backward
        ga, gc, gda, gdc = op(grad.float().contiguous(), a, c, da, dc, nbr, ctx.slope)
        return ga, gc, gda, gdc, None, None, None


class _Leaky(torch.autograd.Function):
    """`vn_leaky_relu` in training (directions of the features' shape), with its fused backward."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, d: torch.Tensor, slope: float) -> torch.Tensor:
        ctx.save_for_backward(x, d)
        ctx.slope = slope
        return torch.ops.efem_vn.leaky(x, d, slope)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        x, d = ctx.saved_tensors
        gx, gd = torch.ops.efem_vn.leaky_backward(grad.float().contiguous(), x, d, ctx.slope)
        return gx, gd, None


def leaky(x: torch.Tensor, d: torch.Tensor, slope: float) -> torch.Tensor:
    """`vn_leaky_relu(x, d, slope)`; in training (`trainable`, ``d`` of ``x``'s shape) one fused pass forward and one
    backward instead of a dozen eager element-wise passes each way (float32 results, also for bfloat16 inputs).
    Inference keeps the eager function, whose roundings the solver's answers were measured with."""
    if d.shape == x.shape and x.dim() >= 2 and x.shape[-2] == 3 and trainable(x, d):
        return _Leaky.apply(x.float().contiguous(), d.float().contiguous(), float(slope))  # type: ignore[no-any-return]
    return vn_leaky_relu(x, d, slope)


def _edge_act_reference(a: torch.Tensor, c: torch.Tensor, da: torch.Tensor, dc: torch.Tensor, nbr: torch.Tensor,
                        slope: float) -> torch.Tensor:
    """Eager ``VN-LeakyReLU(a[nbr] + c; da[nbr] + dc)`` of every edge: ``(B, Nd, k, 3, C)``."""
    b = a.shape[0]
    ar = torch.arange(b, device=a.device).view(b, 1, 1)
    return vn_leaky_relu(a[ar, nbr] + c[:, :, None], da[ar, nbr] + dc[:, :, None], slope)


def _edge_act_trained(a: torch.Tensor, c: torch.Tensor, da: torch.Tensor, dc: torch.Tensor, nbr: torch.Tensor,
                      slope: float, mean: bool = False) -> torch.Tensor:
    """`_edge_act_reference` (or with `mean` its average over each destination's edges, `edge_mean_reference`) with
    the fused forward and backward (training; `trainable` checked by the caller)."""
    f32 = [t.float().contiguous() for t in (a, c, da, dc)]
    return _Edges.apply(*f32, nbr.contiguous(), float(slope), mean)  # type: ignore[no-any-return]


def edge_mean(a: torch.Tensor, c: torch.Tensor, nbr: torch.Tensor, w_dir: torch.Tensor,
              slope: float) -> torch.Tensor:
    """``mean_k VN-LeakyReLU_U(a[nbr] + c)`` with ``U = w_dir`` (`edge_mean_reference`; fused when `usable`, and
    in training with a fused backward when `trainable`: float32 results, also for bfloat16 inputs).

    Args:
        a: ``(B, Ns, 3, C)``.
        c: ``(B, Nd, 3, C)``.
        nbr: ``(B, Nd, k)`` int64 indices into ``Ns``.
        w_dir: ``(C, C)`` direction weights.
        slope: negative slope α.
    """
    da, dc = F.linear(a, w_dir), F.linear(c, w_dir)
    if usable(a, c, da, dc):
        return torch.ops.efem_vn.edge_mean(a, c, da, dc, nbr, float(slope))
    if trainable(a, c, da, dc):
        return _edge_act_trained(a, c, da, dc, nbr, slope, mean=True)
    return edge_mean_reference(a, c, da, dc, nbr, slope)


def attention_reference(v: tuple[torch.Tensor, ...], k: tuple[torch.Tensor, ...], q: torch.Tensor, nbr: torch.Tensor,
                        slope: float, head_dim: int,
                        edge_act: Callable[..., torch.Tensor] = _edge_act_reference) -> torch.Tensor:
    """Eager VN attention of each destination point over its ``k`` neighbours (the spec's chair aggregation).

    Args:
        v: the values' terms ``(a, c, da, dc)`` as `edge_mean_reference` takes them: ``u = act(a[nbr] + c)``.
        k: the keys' terms, likewise: ``κ = act(a[nbr] + c)`` before ChNorm.
        q: ``(B, Nd, 3, C)`` ChNorm'd queries.
        nbr: ``(B, Nd, k)`` int64 indices into the sources.
        slope: negative slope α of both activations.
        head_dim: channels per head.
        edge_act: computes every edge's activation from one of the term tuples (the eager one, or in training
            the fused `_edge_act_trained`).

    Returns:
        ``(B, Nd, 3, C)``: ``Σ_j softmax_j(Σ_{c ∈ head} <q_c, κ_jc> / (‖κ_j‖_F √(3 head_dim))) u_jc``. ChNorm of the
        keys is one scalar per edge, so it divides the per-head dot products instead of the keys.
    """
    u, kraw = edge_act(*v, nbr, slope), edge_act(*k, nbr, slope)  # (B, Nd, k, 3, C)
    heads = kraw.shape[-1] // head_dim
    dots = (q[:, :, None] * kraw).unflatten(-1, (heads, head_dim)).sum(dim=(-3, -1))  # (B, Nd, k, H)
    k_norm = kraw.flatten(-2).norm(dim=-1).clamp_min(EPS)  # (B, Nd, k)
    att = (dots / (k_norm[..., None] * math.sqrt(3 * head_dim))).softmax(dim=2)
    return torch.einsum("bnkh,bnkxhd->bnxhd", att, u.unflatten(-1, (heads, head_dim))).flatten(-2)


def attention(v: tuple[torch.Tensor, ...], k: tuple[torch.Tensor, ...], q: torch.Tensor, nbr: torch.Tensor,
              slope: float, head_dim: int) -> torch.Tensor:
    """`attention_reference`, in one pass per point that never writes the ``k``-fold tensors when `usable`."""
    if usable(*v, *k, q):
        return torch.ops.efem_vn.attention(*v, *k, q, nbr, float(slope), int(head_dim), float(EPS))
    if trainable(*v, *k):
        return attention_reference(v, k, q, nbr, slope, head_dim, edge_act=_edge_act_trained)
    return attention_reference(v, k, q, nbr, slope, head_dim)


def lin_act_mean(x: torch.Tensor, w_lin: torch.Tensor, w_dir: torch.Tensor, slope: float) -> torch.Tensor:
    """``mean_k VN-LeakyReLU_U(W x)`` for ``x (B, Nd, k, 3, C_in)``: one C++ pass when `usable` (the products
    kept per edge, never in memory), else the products here and the fused activation or its reference."""
    if x.dim() == 5 and x.shape[3] == 3 and usable(x, w_lin, w_dir):
        return torch.ops.efem_vn.lin_act_mean(x, w_lin, w_dir, float(slope))
    y = F.linear(x, w_lin)
    d = F.linear(y, w_dir)
    if usable(y, d):
        return torch.ops.efem_vn.act_mean(y, d, float(slope))
    if trainable(y, d):
        return leaky(y, d, slope).mean(dim=2)
    return act_mean_reference(y, d, slope)


def fps(points: torch.Tensor, n_samples: int, *, start: int = 0) -> torch.Tensor:
    """`efem_viz.geometry.fps.farthest_point_sample` (the same indices: the same roundings, the first of equal
    maxima) in one C++ loop per batch row when `usable` and the points are finite, instead of a Python loop of
    kernel launches per sample."""
    from efem_viz.geometry.fps import farthest_point_sample

    if points.ndim != 3 or not 1 <= n_samples <= points.shape[1] or not 0 <= start < points.shape[1]:
        return farthest_point_sample(points, n_samples, start=start)  # its one error message
    with torch.no_grad(), torch.autocast(points.device.type, enabled=False):
        p = points.detach()
        if p.shape[2] < 1 or not usable(p) or not bool(torch.isfinite(p).all()):
            return farthest_point_sample(points, n_samples, start=start)
        return torch.ops.efem_vn.fps(p, int(n_samples), int(start))


def knn(query: torch.Tensor, ref: torch.Tensor, k: int) -> torch.Tensor:
    """`efem_viz.geometry.knn.knn_indices` (the same neighbours, ascending distance), with the selection in one
    pass per row when `usable` instead of a `topk` over the distance matrix: the distances are formed as the
    eager formula forms them (float32, the same rounding). Where equal distances among a row's k all belong to
    identical reference rows (duplicate points: the M-step draws with replacement) the row keeps its one pass,
    equal distances by ascending index: indices may differ from `topk`'s there, never what they gather. A row
    with equal distances between different points takes torch's own selection, so its indices equal `topk`'s.
    The Gram rows come from the CPU GEMM a slab of query rows at a time (`knn` in `vn_kernels.cpp`): the batched
    product's entries, without the (B, Nq, Nr) matrix in memory.
    Half-precision features (a bf16 autocast's, in training) are selected in float32, as `knn_indices` does.

    Args:
        query: ``(B, Nq, D)`` float.
        ref: ``(B, Nr, D)`` float, same dtype/device.
        k: neighbours per query, ``1 <= k <= Nr``.

    Returns:
        ``(B, Nq, k)`` int64 indices into ``Nr``.
    """
    from efem_viz.geometry.knn import knn_indices

    if (query.ndim != 3 or ref.ndim != 3 or query.shape[0] != ref.shape[0] or query.shape[2] != ref.shape[2]
            or not 1 <= k <= ref.shape[1]):
        return knn_indices(query, ref, k)  # its one error message
    with torch.no_grad(), torch.autocast(query.device.type, enabled=False):
        q, r = query.detach(), ref.detach()
        if q.dtype in (torch.bfloat16, torch.float16) and r.dtype == q.dtype:  # an autocast's features in training
            q, r = q.float(), r.float()  # the float32 distances `knn_indices` forms for them
        if not usable(q, r):
            return knn_indices(query, ref, k)
        return torch.ops.efem_vn.knn(q, r, (q * q).sum(-1), (r * r).sum(-1), int(k))


DECODER_TILE = 256
"""Rows per tile of the fused decoder pass: every activation the tile keeps for its backward (width 128, two
blocks: 5 x 128 KB) stays in the core's L2."""
DECODER_TILE_BF16 = 1024
"""Rows per tile of its bf16 pass on a CPU without AMX, whose bf16 GEMM gained more from taller tiles than the
cache lost (per pass on a Zen 4 core, tiles of 256 / 512 / 1024 / 2048 rows: 1.2 / 1.4 / 1.55 / 1.5x the float32
pass at 256; `bench/decoder_kernel.py`; measured when the pass's products had bf16 results, not re-measured
since)."""
DECODER_TILE_BF16_AMX = 256
"""The same where the CPU has AMX: its packed bf16 micro-kernel has no per-call setup to spread, and tiles that stay
in L2 win (replayed E-step decodes of a real frame on an AMX Xeon, tiles of 128 / 256 / 512 / 1024 / 2048 rows:
1.05 / 1.00 / 1.01 / 1.13-1.26 / 1.27-1.50x the time at 256)."""


def bf16_tile() -> int:
    """Rows per tile of the bf16 pass on this CPU (`DECODER_TILE_BF16_AMX` where it has AMX tiles)."""
    from efem_viz.prior.config import cpu_has_amx

    return DECODER_TILE_BF16_AMX if cpu_has_amx() else DECODER_TILE_BF16


def autocast_bf16() -> bool:
    """Whether a CPU bf16 autocast is on (`EMConfig.compute.matmul_dtype` "bfloat16"): `decoder_band` then
    rounds its hidden products' operands to bf16, as the autocast's linear layers would."""
    return torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu") == torch.bfloat16


def decoder_band(q: torch.Tensor, mt: torch.Tensor, blocks: list[tuple[torch.Tensor, ...]], w_out: torch.Tensor,
                 b_out: float, within: float, use_qnorm: bool, *, bf16: bool | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The decoder's inference pass in one C++ loop over tiles (`SDFDecoder.sdf_and_band_grad` is the same
    math; None where the kernels do not serve these tensors: the caller runs its eager code).

    Args:
        q: ``(B, Q, 3)`` canonical queries.
        mt: ``(B, 5, H)`` per latent: the rows of ``Mᵀ``, ``a_q`` and the folded bias.
        blocks: ``(W0, b0, W1, b1)`` of each residual block, as ``nn.Linear`` stores them.
        w_out: ``(H,)`` output weights.
        b_out: output bias.
        within: band half-width; negative: the SDF only.
        use_qnorm: whether ``a_q ‖q‖`` enters the first layer.
        bf16: the hidden layers' matrix products (forward and the band's backward) with bfloat16 operands and
            float32 results; the first layer, biases, ReLU, residual stream, output and the gradient's sums stay
            float32. None: whether a CPU bf16 autocast is on (`autocast_bf16`).

    Returns:
        ``sdf (B, Q)``, ``dq (B, Q, 3)`` (∂sdf/∂q, zeros outside the band), ``band (B, Q)`` bool, float32.
    """
    flat = [t for blk in blocks for t in blk]
    on = autocast_bf16()
    if not usable(q, mt, w_out, *flat, autocast_ok=on):
        return None
    w0, b0, w1, b1 = ([blk[i] for blk in blocks] for i in range(4))
    half = on if bf16 is None else bool(bf16)
    with torch.autocast("cpu", enabled=False):
        return torch.ops.efem_vn.decoder_band(q, mt, w0, b0, w1, b1, w_out, float(b_out), float(within),
                                              bool(use_qnorm), bf16_tile() if half else DECODER_TILE, half)
