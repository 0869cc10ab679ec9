// Fused VN edge kernels of the encoder and the decoder's inference pass (efem_viz/prior/fused.py builds and loads
// this file; the Python references there are the same math). CPU, float32; every neighbour index is checked
// before use.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <ATen/native/CPUBlas.h>
#include <torch/library.h>
#ifdef __AVX512F__
#include <immintrin.h>
#endif
#include <algorithm>
#include <utility>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <tuple>
#include <limits>
#include <optional>
#include <vector>

namespace {

#ifdef __AVX512F__
constexpr int64_t kLanes = 16;  // floats in one AVX-512 register
#else
constexpr int64_t kLanes = 0;
#endif

#if defined(__GNUC__)
#define EFEM_INLINE inline __attribute__((always_inline))  // into each loop that calls it: vectorised there
#else
#define EFEM_INLINE inline
#endif

template <bool Accumulate>
EFEM_INLINE void vn_leaky(const float* __restrict x, const float* __restrict d, float* __restrict out, int64_t C,
                          float f) {
  // VN-LeakyReLU(x; d) of one edge, added to out[0..3C) (Accumulate) or written there; x, d, out are (3, C) with
  // C contiguous and never overlap (`__restrict`: the compiler vectorises the loop over channels wherever it is
  // inlined; without it, whether it did depended on the other kernels in this file)
  for (int64_t ch = 0; ch < C; ++ch) {
    const float x0 = x[ch], x1 = x[C + ch], x2 = x[2 * C + ch];
    const float d0 = d[ch], d1 = d[C + ch], d2 = d[2 * C + ch];
    const float dot = x0 * d0 + x1 * d1 + x2 * d2;
    const float dn2 = d0 * d0 + d1 * d1 + d2 * d2;
    const float coef = std::min(dot, 0.0f) / std::max(dn2, 1e-24f) * f;
    if constexpr (Accumulate) {
      out[ch] += x0 - coef * d0;
      out[C + ch] += x1 - coef * d1;
      out[2 * C + ch] += x2 - coef * d2;
    } else {
      out[ch] = x0 - coef * d0;
      out[C + ch] = x1 - coef * d1;
      out[2 * C + ch] = x2 - coef * d2;
    }
  }
}

EFEM_INLINE void vn_acc(const float* x, const float* d, float* acc, int64_t C, float f) { vn_leaky<true>(x, d, acc, C, f); }
EFEM_INLINE void vn_act(const float* x, const float* d, float* out, int64_t C, float f) { vn_leaky<false>(x, d, out, C, f); }

void check_edge_terms(const at::Tensor& a_, const at::Tensor& c_, const at::Tensor& da_, const at::Tensor& dc_,
                      const at::Tensor& nbr_) {
  TORCH_CHECK(a_.dim() == 4 && a_.size(2) == 3 && a_.scalar_type() == at::kFloat, "a must be (B, Ns, 3, C) float32");
  TORCH_CHECK(c_.dim() == 4 && c_.size(0) == a_.size(0) && c_.size(2) == 3 && c_.size(3) == a_.size(3) &&
              c_.scalar_type() == at::kFloat, "c must be (B, Nd, 3, C) float32");
  TORCH_CHECK(da_.sizes() == a_.sizes() && dc_.sizes() == c_.sizes() && da_.scalar_type() == at::kFloat &&
              dc_.scalar_type() == at::kFloat, "da/dc must match a/c");
  TORCH_CHECK(nbr_.dim() == 3 && nbr_.size(0) == a_.size(0) && nbr_.size(1) == c_.size(1) &&
              nbr_.scalar_type() == at::kLong, "nbr must be (B, Nd, k) int64");
  TORCH_CHECK(a_.device().is_cpu(), "CPU tensors only");
  TORCH_CHECK(nbr_.size(2) > 0 || c_.numel() == 0, "k must be >= 1");
  const auto nbr = nbr_.contiguous();
  const int64_t* pn = nbr.data_ptr<int64_t>();
  const int64_t n_idx = nbr.numel(), Ns = a_.size(1);
  for (int64_t t = 0; t < n_idx; ++t) TORCH_CHECK(pn[t] >= 0 && pn[t] < Ns, "neighbour index out of range");
}

template <bool Mean>
at::Tensor edge_forward(const at::Tensor& a_, const at::Tensor& c_, const at::Tensor& da_, const at::Tensor& dc_,
                        const at::Tensor& nbr_, double slope) {
  // VN-LeakyReLU(a[nbr] + c; da[nbr] + dc) of every edge: averaged over each destination's k edges (Mean, `edge_mean`,
  // (B, Nd, 3, C)) or every edge's own ((B, Nd, k, 3, C), `edge_act`).
  check_edge_terms(a_, c_, da_, dc_, nbr_);
  const auto a = a_.contiguous(), c = c_.contiguous(), da = da_.contiguous(), dc = dc_.contiguous();
  const auto nbr = nbr_.contiguous();
  const int64_t B = a.size(0), Ns = a.size(1), C = a.size(3), Nd = c.size(1), K = nbr.size(2);
  auto out = Mean ? at::empty({B, Nd, 3, C}, a.options()) : at::empty({B, Nd, K, 3, C}, a.options());
  if (out.numel() == 0) return out;
  const int64_t* pn = nbr.data_ptr<int64_t>();
  const float* pa = a.data_ptr<float>();
  const float* pc = c.data_ptr<float>();
  const float* pda = da.data_ptr<float>();
  const float* pdc = dc.data_ptr<float>();
  float* po = out.data_ptr<float>();
  const float f = 1.0f - static_cast<float>(slope);
  const float invk = 1.0f / static_cast<float>(K);
  const int64_t S = 3 * C;
  at::parallel_for(0, B * Nd, 16, [&](int64_t begin, int64_t end) {
    std::vector<float> x(S), d(S), acc(Mean ? S : 0);
    for (int64_t bi = begin; bi < end; ++bi) {
      const int64_t b = bi / Nd;
      const float* ci = pc + bi * S;
      const float* dci = pdc + bi * S;
      if constexpr (Mean) std::fill(acc.begin(), acc.end(), 0.0f);
      for (int64_t j = 0; j < K; ++j) {
        const int64_t s = pn[bi * K + j];
        const float* aj = pa + (b * Ns + s) * S;
        const float* daj = pda + (b * Ns + s) * S;
        for (int64_t t = 0; t < S; ++t) { x[t] = aj[t] + ci[t]; d[t] = daj[t] + dci[t]; }
        if constexpr (Mean) {
          vn_acc(x.data(), d.data(), acc.data(), C, f);
        } else {
          vn_act(x.data(), d.data(), po + (bi * K + j) * S, C, f);
        }
      }
      if constexpr (Mean) {
        float* o = po + bi * S;
        for (int64_t t = 0; t < S; ++t) o[t] = acc[t] * invk;
      }
    }
  });
  return out;
}

at::Tensor edge_mean(const at::Tensor& a, const at::Tensor& c, const at::Tensor& da, const at::Tensor& dc,
                     const at::Tensor& nbr, double slope) {
  return edge_forward<true>(a, c, da, dc, nbr, slope);
}

at::Tensor edge_act(const at::Tensor& a, const at::Tensor& c, const at::Tensor& da, const at::Tensor& dc,
                    const at::Tensor& nbr, double slope) {
  return edge_forward<false>(a, c, da, dc, nbr, slope);
}

EFEM_INLINE void vn_leaky_grad(const float* __restrict x, const float* __restrict d, const float* __restrict g,
                               float* __restrict gx, float* __restrict gd, int64_t C, float f) {
  // Gradients of VN-LeakyReLU(x; d) of one edge for the output gradient g, written to gx and gd (each (3, C)):
  // with dot = <x, d>, D = max(|d|^2, 1e-24) and coef = min(dot, 0) f / D, y = x - coef d gives
  //   dL/dx = g - <g, d> f / D d and dL/dd = -coef g - <g, d> (f / D x - 2 coef / D d)  where dot <= 0,
  //   dL/dx = g and dL/dd = 0 elsewhere;
  // the 2 coef / D d term only where |d|^2 >= 1e-24 (torch's clamp passes gradients at its bounds: so here).
  for (int64_t ch = 0; ch < C; ++ch) {
    const float x0 = x[ch], x1 = x[C + ch], x2 = x[2 * C + ch];
    const float d0 = d[ch], d1 = d[C + ch], d2 = d[2 * C + ch];
    const float g0 = g[ch], g1 = g[C + ch], g2 = g[2 * C + ch];
    const float dot = x0 * d0 + x1 * d1 + x2 * d2;
    const float dn2 = d0 * d0 + d1 * d1 + d2 * d2;
    const float den = std::max(dn2, 1e-24f);
    const float on = dot <= 0.0f ? 1.0f : 0.0f;
    const float s = on * f / den;
    const float coef = s * dot;
    const float gdd = g0 * d0 + g1 * d1 + g2 * d2;
    const float k = gdd * s;
    const float q = dn2 >= 1e-24f ? 2.0f * gdd * coef / den : 0.0f;
    gx[ch] = g0 - k * d0;
    gx[C + ch] = g1 - k * d1;
    gx[2 * C + ch] = g2 - k * d2;
    gd[ch] = -coef * g0 - k * x0 + q * d0;
    gd[C + ch] = -coef * g1 - k * x1 + q * d1;
    gd[2 * C + ch] = -coef * g2 - k * x2 + q * d2;
  }
}

template <bool Mean>
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> edge_backward(
    const at::Tensor& grad_, const at::Tensor& a_, const at::Tensor& c_, const at::Tensor& da_, const at::Tensor& dc_,
    const at::Tensor& nbr_, double slope) {
  // Gradients with respect to a, c, da and dc of `edge_mean` (Mean: grad (B, Nd, 3, C), each edge takes 1/k of
  // it) or of `edge_act` (grad (B, Nd, k, 3, C), one per edge). The source terms gather from every destination that
  // names them, so the work is split by batch row: each thread owns its rows' sources, and the sums run in one
  // fixed order (deterministic for any thread count).
  check_edge_terms(a_, c_, da_, dc_, nbr_);
  const int64_t B = a_.size(0), Ns = a_.size(1), C = a_.size(3), Nd = c_.size(1), K = nbr_.size(2);
  if constexpr (Mean) {
    TORCH_CHECK(grad_.sizes() == c_.sizes() && grad_.scalar_type() == at::kFloat, "grad must match c");
  } else {
    TORCH_CHECK(grad_.dim() == 5 && grad_.size(0) == B && grad_.size(1) == Nd && grad_.size(2) == K &&
                grad_.size(3) == 3 && grad_.size(4) == C && grad_.scalar_type() == at::kFloat,
                "grad must be (B, Nd, k, 3, C) float32");
  }
  const auto a = a_.contiguous(), c = c_.contiguous(), da = da_.contiguous(), dc = dc_.contiguous();
  const auto grad = grad_.contiguous(), nbr = nbr_.contiguous();
  auto ga = at::zeros_like(a), gda = at::zeros_like(a);
  auto gc = at::zeros_like(c), gdc = at::zeros_like(c);
  if (c.numel() == 0 || a.numel() == 0) return {ga, gc, gda, gdc};
  const int64_t* pn = nbr.data_ptr<int64_t>();
  const float* pa = a.data_ptr<float>();
  const float* pc = c.data_ptr<float>();
  const float* pda = da.data_ptr<float>();
  const float* pdc = dc.data_ptr<float>();
  const float* pg = grad.data_ptr<float>();
  float* pga = ga.data_ptr<float>();
  float* pgda = gda.data_ptr<float>();
  float* pgc = gc.data_ptr<float>();
  float* pgdc = gdc.data_ptr<float>();
  const float f = 1.0f - static_cast<float>(slope);
  const float invk = 1.0f / static_cast<float>(K);
  const int64_t S = 3 * C;
  at::parallel_for(0, B, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> x(S), d(S), g(S), gx(S), gd(S);
    for (int64_t b = begin; b < end; ++b) {
      for (int64_t i = 0; i < Nd; ++i) {
        const int64_t bi = b * Nd + i;
        const float* ci = pc + bi * S;
        const float* dci = pdc + bi * S;
        float* gci = pgc + bi * S;
        float* gdci = pgdc + bi * S;
        if constexpr (Mean) {
          for (int64_t t = 0; t < S; ++t) g[t] = pg[bi * S + t] * invk;
        }
        for (int64_t j = 0; j < K; ++j) {
          const int64_t src = (b * Ns + pn[bi * K + j]) * S;
          const float* aj = pa + src;
          const float* daj = pda + src;
          for (int64_t t = 0; t < S; ++t) { x[t] = aj[t] + ci[t]; d[t] = daj[t] + dci[t]; }
          const float* ge = Mean ? g.data() : pg + (bi * K + j) * S;
          vn_leaky_grad(x.data(), d.data(), ge, gx.data(), gd.data(), C, f);
          float* gaj = pga + src;
          float* gdaj = pgda + src;
          for (int64_t t = 0; t < S; ++t) {
            gaj[t] += gx[t];
            gci[t] += gx[t];
            gdaj[t] += gd[t];
            gdci[t] += gd[t];
          }
        }
      }
    }
  });
  return {ga, gc, gda, gdc};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> edge_mean_backward(
    const at::Tensor& grad, const at::Tensor& a, const at::Tensor& c, const at::Tensor& da, const at::Tensor& dc,
    const at::Tensor& nbr, double slope) {
  return edge_backward<true>(grad, a, c, da, dc, nbr, slope);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> edge_act_backward(
    const at::Tensor& grad, const at::Tensor& a, const at::Tensor& c, const at::Tensor& da, const at::Tensor& dc,
    const at::Tensor& nbr, double slope) {
  return edge_backward<false>(grad, a, c, da, dc, nbr, slope);
}

at::Tensor leaky(const at::Tensor& x_, const at::Tensor& d_, double slope) {
  // VN-LeakyReLU(x; d) of (..., 3, C) features with directions of the same shape.
  TORCH_CHECK(x_.dim() >= 2 && x_.size(-2) == 3 && x_.scalar_type() == at::kFloat, "x must be (..., 3, C) float32");
  TORCH_CHECK(d_.sizes() == x_.sizes() && d_.scalar_type() == at::kFloat, "d must match x");
  TORCH_CHECK(x_.device().is_cpu(), "CPU tensors only");
  const auto x = x_.contiguous(), d = d_.contiguous();
  auto out = at::empty_like(x);
  const int64_t C = x.size(-1), S = 3 * C, M = C > 0 ? x.numel() / S : 0;
  if (M == 0) return out;
  const float* px = x.data_ptr<float>();
  const float* pd = d.data_ptr<float>();
  float* po = out.data_ptr<float>();
  const float f = 1.0f - static_cast<float>(slope);
  at::parallel_for(0, M, 64, [&](int64_t begin, int64_t end) {
    for (int64_t m = begin; m < end; ++m) vn_act(px + m * S, pd + m * S, po + m * S, C, f);
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> leaky_backward(const at::Tensor& grad_, const at::Tensor& x_, const at::Tensor& d_,
                                                  double slope) {
  // Gradients of `leaky` with respect to x and d.
  TORCH_CHECK(x_.dim() >= 2 && x_.size(-2) == 3 && x_.scalar_type() == at::kFloat, "x must be (..., 3, C) float32");
  TORCH_CHECK(d_.sizes() == x_.sizes() && d_.scalar_type() == at::kFloat, "d must match x");
  TORCH_CHECK(grad_.sizes() == x_.sizes() && grad_.scalar_type() == at::kFloat, "grad must match x");
  TORCH_CHECK(x_.device().is_cpu(), "CPU tensors only");
  const auto x = x_.contiguous(), d = d_.contiguous(), grad = grad_.contiguous();
  auto gx = at::empty_like(x), gd = at::empty_like(x);
  const int64_t C = x.size(-1), S = 3 * C, M = C > 0 ? x.numel() / S : 0;
  if (M == 0) return {gx, gd};
  const float* px = x.data_ptr<float>();
  const float* pd = d.data_ptr<float>();
  const float* pg = grad.data_ptr<float>();
  float* pgx = gx.data_ptr<float>();
  float* pgd = gd.data_ptr<float>();
  const float f = 1.0f - static_cast<float>(slope);
  at::parallel_for(0, M, 64, [&](int64_t begin, int64_t end) {
    for (int64_t m = begin; m < end; ++m) {
      vn_leaky_grad(px + m * S, pd + m * S, pg + m * S, pgx + m * S, pgd + m * S, C, f);
    }
  });
  return {gx, gd};
}

at::Tensor act_mean(const at::Tensor& x_, const at::Tensor& d_, double slope) {
  TORCH_CHECK(x_.dim() == 5 && x_.size(3) == 3 && x_.scalar_type() == at::kFloat, "x must be (B, N, k, 3, C) float32");
  TORCH_CHECK(d_.sizes() == x_.sizes() && d_.scalar_type() == at::kFloat, "d must match x");
  TORCH_CHECK(x_.device().is_cpu(), "CPU tensors only");
  const auto x = x_.contiguous(), d = d_.contiguous();
  const int64_t B = x.size(0), N = x.size(1), K = x.size(2), C = x.size(4), S = 3 * C;
  auto out = at::empty({B, N, 3, C}, x.options());
  if (out.numel() == 0) return out;
  TORCH_CHECK(K > 0, "k must be >= 1");
  const float* px = x.data_ptr<float>();
  const float* pd = d.data_ptr<float>();
  float* po = out.data_ptr<float>();
  const float f = 1.0f - static_cast<float>(slope);
  const float invk = 1.0f / static_cast<float>(K);
  at::parallel_for(0, B * N, 16, [&](int64_t begin, int64_t end) {
    std::vector<float> acc(S);
    for (int64_t bi = begin; bi < end; ++bi) {
      std::fill(acc.begin(), acc.end(), 0.0f);
      for (int64_t j = 0; j < K; ++j) vn_acc(px + (bi * K + j) * S, pd + (bi * K + j) * S, acc.data(), C, f);
      float* o = po + bi * S;
      for (int64_t t = 0; t < S; ++t) o[t] = acc[t] * invk;
    }
  });
  return out;
}

at::Tensor lin_act_mean(const at::Tensor& x_, const at::Tensor& w_, const at::Tensor& u_, double slope) {
  // mean_k VN-LeakyReLU_U(W x) for x (B, N, k, 3, Cin): `act_mean(linear(x, W), linear(linear(x, W), U))` in one
  // pass without the two (B, N, k, 3, C) products in memory. Each product entry is the chain a_0 w_0, then
  // fma(a_i, w_i, .) in input order (the order the CPU GEMM takes for these small products on the machines
  // measured, so the result is the same bits there; the same math to rounding anywhere), then act_mean's own
  // activation and mean.
  TORCH_CHECK(x_.dim() == 5 && x_.size(3) == 3 && x_.scalar_type() == at::kFloat, "x must be (B, N, k, 3, Cin) float32");
  TORCH_CHECK(w_.dim() == 2 && w_.size(1) == x_.size(4) && w_.scalar_type() == at::kFloat, "w must be (C, Cin) float32");
  TORCH_CHECK(u_.dim() == 2 && u_.size(0) == w_.size(0) && u_.size(1) == w_.size(0) && u_.scalar_type() == at::kFloat,
              "u must be (C, C) float32");
  TORCH_CHECK(x_.device().is_cpu() && w_.device().is_cpu() && u_.device().is_cpu(), "CPU tensors only");
  const auto x = x_.contiguous();
  const auto wt = w_.t().contiguous(), ut = u_.t().contiguous();  // (Cin, C), (C, C): a row per input channel
  const int64_t B = x.size(0), N = x.size(1), K = x.size(2), Cin = x.size(4), C = w_.size(0), S = 3 * C;
  auto out = at::empty({B, N, 3, C}, x.options());
  if (out.numel() == 0) return out;
  TORCH_CHECK(K > 0, "k must be >= 1");
  TORCH_CHECK(Cin > 0, "x needs at least one channel");
  const float* px = x.data_ptr<float>();
  const float* pw = wt.data_ptr<float>();
  const float* pu = ut.data_ptr<float>();
  float* po = out.data_ptr<float>();
  const float f = 1.0f - static_cast<float>(slope);
  const float invk = 1.0f / static_cast<float>(K);
  // product entries: out[c] = chain over i of a[i] * m[i][c] (m: rows of n contiguous entries)
  auto chain = [](const float* a, const float* m, int64_t n_in, int64_t n, float* o) {
    int64_t c = 0;
#ifdef __AVX512F__
    for (; c + kLanes <= n; c += kLanes) {
      __m512 acc = _mm512_mul_ps(_mm512_set1_ps(a[0]), _mm512_loadu_ps(m + c));
      for (int64_t i = 1; i < n_in; ++i) acc = _mm512_fmadd_ps(_mm512_set1_ps(a[i]), _mm512_loadu_ps(m + i * n + c), acc);
      _mm512_storeu_ps(o + c, acc);
    }
#endif
    for (; c < n; ++c) {
      float acc = a[0] * m[c];
      for (int64_t i = 1; i < n_in; ++i) {
#ifdef __FMA__
        acc = std::fma(a[i], m[i * n + c], acc);
#else
        acc = a[i] * m[i * n + c] + acc;
#endif
      }
      o[c] = acc;
    }
  };
  at::parallel_for(0, B * N, 16, [&](int64_t begin, int64_t end) {
    std::vector<float> y(S), d(S), acc(S);
    for (int64_t bi = begin; bi < end; ++bi) {
      std::fill(acc.begin(), acc.end(), 0.0f);
      for (int64_t j = 0; j < K; ++j) {
        const float* e = px + (bi * K + j) * 3 * Cin;
        for (int64_t r = 0; r < 3; ++r) {
          chain(e + r * Cin, pw, Cin, C, y.data() + r * C);
          chain(y.data() + r * C, pu, C, C, d.data() + r * C);
        }
        vn_acc(y.data(), d.data(), acc.data(), C, f);
      }
      float* o = po + bi * S;
      for (int64_t t = 0; t < S; ++t) o[t] = acc[t] * invk;
    }
  });
  return out;
}

at::Tensor attention(const at::Tensor& av_, const at::Tensor& cv_, const at::Tensor& dav_, const at::Tensor& dcv_,
                     const at::Tensor& ak_, const at::Tensor& ck_, const at::Tensor& dak_, const at::Tensor& dck_,
                     const at::Tensor& q_, const at::Tensor& nbr_, double slope, int64_t head_dim, double eps) {
  // VN attention over each point's k neighbours in one pass (fused.attention_reference is the same math): values
  // u = act(av[nbr] + cv), keys kappa = act(ak[nbr] + ck) (directions da[nbr] + dc likewise), per head
  // logits sum_{c in head} <q_c, kappa_c> / (max(|kappa|_F, eps) sqrt(3 head_dim)), softmax over the neighbours,
  // out = sum_j att_j u_j.
  TORCH_CHECK(av_.dim() == 4 && av_.size(2) == 3 && av_.scalar_type() == at::kFloat, "av must be (B, Ns, 3, C) float32");
  const int64_t B = av_.size(0), Ns = av_.size(1), C = av_.size(3);
  TORCH_CHECK(cv_.dim() == 4 && cv_.size(0) == B && cv_.size(2) == 3 && cv_.size(3) == C, "cv must be (B, Nd, 3, C)");
  const int64_t Nd = cv_.size(1);
  for (const at::Tensor* t : {&av_, &dav_, &ak_, &dak_})
    TORCH_CHECK(t->sizes() == av_.sizes() && t->scalar_type() == at::kFloat, "source terms must be (B, Ns, 3, C) float32");
  for (const at::Tensor* t : {&cv_, &dcv_, &ck_, &dck_, &q_})
    TORCH_CHECK(t->sizes() == cv_.sizes() && t->scalar_type() == at::kFloat, "point terms must be (B, Nd, 3, C) float32");
  TORCH_CHECK(nbr_.dim() == 3 && nbr_.size(0) == B && nbr_.size(1) == Nd && nbr_.scalar_type() == at::kLong,
              "nbr must be (B, Nd, k) int64");
  TORCH_CHECK(head_dim >= 1 && C % head_dim == 0, "C must be a multiple of head_dim");
  TORCH_CHECK(av_.device().is_cpu(), "CPU tensors only");
  const auto av = av_.contiguous(), cv = cv_.contiguous(), dav = dav_.contiguous(), dcv = dcv_.contiguous();
  const auto ak = ak_.contiguous(), ck = ck_.contiguous(), dak = dak_.contiguous(), dck = dck_.contiguous();
  const auto q = q_.contiguous(), nbr = nbr_.contiguous();
  const int64_t K = nbr.size(2), S = 3 * C, H = C / head_dim;
  auto out = at::empty({B, Nd, 3, C}, av.options());
  if (out.numel() == 0) return out;
  TORCH_CHECK(K > 0, "k must be >= 1");
  const int64_t* pn = nbr.data_ptr<int64_t>();
  for (int64_t t = 0; t < nbr.numel(); ++t) TORCH_CHECK(pn[t] >= 0 && pn[t] < Ns, "neighbour index out of range");
  const float *pav = av.data_ptr<float>(), *pcv = cv.data_ptr<float>(), *pdav = dav.data_ptr<float>();
  const float *pdcv = dcv.data_ptr<float>(), *pak = ak.data_ptr<float>(), *pck = ck.data_ptr<float>();
  const float *pdak = dak.data_ptr<float>(), *pdck = dck.data_ptr<float>(), *pq = q.data_ptr<float>();
  float* po = out.data_ptr<float>();
  const float f = 1.0f - static_cast<float>(slope);
  const float epsf = static_cast<float>(eps);
  const float scale = 1.0f / std::sqrt(3.0f * static_cast<float>(head_dim));
  at::parallel_for(0, B * Nd, 8, [&](int64_t begin, int64_t end) {
    std::vector<float> x(S), d(S), kap(S), u(K * S), logit(K * H);
    for (int64_t bi = begin; bi < end; ++bi) {
      const int64_t b = bi / Nd;
      const float* qi = pq + bi * S;
      for (int64_t j = 0; j < K; ++j) {
        const int64_t s = (b * Ns + pn[bi * K + j]) * S;
        for (int64_t t = 0; t < S; ++t) { x[t] = pav[s + t] + pcv[bi * S + t]; d[t] = pdav[s + t] + pdcv[bi * S + t]; }
        vn_act(x.data(), d.data(), u.data() + j * S, C, f);
        for (int64_t t = 0; t < S; ++t) { x[t] = pak[s + t] + pck[bi * S + t]; d[t] = pdak[s + t] + pdck[bi * S + t]; }
        vn_act(x.data(), d.data(), kap.data(), C, f);
        float n2 = 0.0f;
        for (int64_t t = 0; t < S; ++t) n2 += kap[t] * kap[t];
        const float inv = scale / std::max(std::sqrt(n2), epsf);
        for (int64_t h = 0; h < H; ++h) {
          float acc = 0.0f;
          for (int64_t r = 0; r < 3; ++r)
            for (int64_t ch = h * head_dim; ch < (h + 1) * head_dim; ++ch) acc += qi[r * C + ch] * kap[r * C + ch];
          logit[j * H + h] = acc * inv;
        }
      }
      for (int64_t h = 0; h < H; ++h) {  // softmax over the neighbours, per head
        float mx = -std::numeric_limits<float>::infinity();
        for (int64_t j = 0; j < K; ++j) mx = std::max(mx, logit[j * H + h]);
        float z = 0.0f;
        for (int64_t j = 0; j < K; ++j) { logit[j * H + h] = std::exp(logit[j * H + h] - mx); z += logit[j * H + h]; }
        for (int64_t j = 0; j < K; ++j) logit[j * H + h] /= z;
      }
      float* o = po + bi * S;
      std::fill(o, o + S, 0.0f);
      for (int64_t j = 0; j < K; ++j) {
        const float* uj = u.data() + j * S;
        for (int64_t r = 0; r < 3; ++r)
          for (int64_t ch = 0; ch < C; ++ch) o[r * C + ch] += logit[j * H + ch / head_dim] * uj[r * C + ch];
      }
    }
  });
  return out;
}

inline bool topk_less(const std::pair<float, int64_t>& x, const std::pair<float, int64_t>& y) {
  // torch's comparator of topk(largest=False): NaN sorts last
  return (!std::isnan(x.first) && std::isnan(y.first)) || (x.first < y.first);
}

void topk_smallest_like_torch(const float* d, int64_t n, int64_t k, int64_t* out,
                              std::vector<std::pair<float, int64_t>>& queue) {
  // torch.topk(largest=False, sorted=True) of one row, step for step as ATen's CPU loop does it (TopKImpl.h): the
  // same algorithms on the same (value, index) pairs, so equal distances come out in torch's order
  queue.resize(n);
  for (int64_t j = 0; j < n; ++j) queue[j] = {d[j], j};
  if (k * 64 <= n) {
    std::partial_sort(queue.begin(), queue.begin() + k, queue.end(), topk_less);
  } else {
    std::nth_element(queue.begin(), queue.begin() + k - 1, queue.end(), topk_less);
    std::sort(queue.begin(), queue.begin() + k - 1, topk_less);
  }
  for (int64_t j = 0; j < k; ++j) out[j] = queue[j].second;
}

#ifdef __AVX512F__
// The 16 smallest of d[0, n) in ascending order into bd / bi, exactly as the insertion pass leaves them (equal
// distances after the ones already there, the first ones kept at the edge), with the sorted buffer held in one
// register of distances and one of indices: an entry that enters shifts the larger ones up by one lane. False
// (nothing written) where fewer than 16 finite entries entered (infinite distances): the caller's loop decides.
bool select16(const float* d, int64_t n, float* bd, int64_t* bi) {
  __m512 buf = _mm512_set1_ps(std::numeric_limits<float>::infinity());
  __m512i ids = _mm512_set1_epi32(-1);
  const __m512i up = _mm512_set_epi32(14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0, 0);
  const __m512i top = _mm512_set1_epi32(15);
  auto insert = [&](int64_t j) {
    const __m512 v = _mm512_set1_ps(d[j]);
    const __mmask16 m = _mm512_cmp_ps_mask(v, buf, _CMP_LT_OQ);  // the lanes above it: a suffix, buf is sorted
    if (!m) return;
    const __mmask16 first = m & static_cast<__mmask16>(-m);
    buf = _mm512_mask_mov_ps(_mm512_mask_mov_ps(buf, m, _mm512_permutexvar_ps(up, buf)), first, v);
    ids = _mm512_mask_mov_epi32(_mm512_mask_mov_epi32(ids, m, _mm512_permutexvar_epi32(up, ids)), first,
                                _mm512_set1_epi32(static_cast<int32_t>(j)));
  };
  int64_t j = 0;
  for (; j + kLanes <= n; j += kLanes) {  // a lane above the 16th distance at its block's start stays above it
    __mmask16 m = _mm512_cmp_ps_mask(_mm512_loadu_ps(d + j), _mm512_permutexvar_ps(top, buf), _CMP_LT_OQ);
    while (m) {
      insert(j + __builtin_ctz(m));
      m &= m - 1;
    }
  }
  for (; j < n; ++j) insert(j);
  alignas(64) int32_t out[16];
  _mm512_store_epi32(out, ids);
  if (out[15] < 0) return false;
  _mm512_storeu_ps(bd, buf);
  for (int i = 0; i < 16; ++i) bi[i] = out[i];
  return true;
}
#endif

#if defined(__GNUC__) && !defined(__clang__)
#define EFEM_NO_CONTRACT __attribute__((optimize("fp-contract=off")))
#else
#define EFEM_NO_CONTRACT  // clang contracts within one expression only; the squares and sums below are separate
#endif

// One batch row of farthest-point sampling, rounding for rounding the eager loop of `geometry.fps`: per component
// the difference, its square, the sum over components in order (no fused multiply-add), the running minimum and
// the first index of its maximum. pts: (D, N) component-major; out: n_samples indices.
EFEM_NO_CONTRACT void fps_row(const float* pts, int64_t D, int64_t N, int64_t stride, int64_t n_samples,
                              int64_t start, int64_t* out, float* dist, float* dd) {
  std::fill(dist, dist + N, std::numeric_limits<float>::infinity());
  int64_t cur = start;
  for (int64_t i = 0; i < n_samples; ++i) {
    out[i] = cur;
    for (int64_t c = 0; c < D; ++c) {
      const float* pc = pts + c * stride;
      const float x = pc[cur];
      if (c == 0) {
        for (int64_t j = 0; j < N; ++j) {
          const float diff = pc[j] - x;
          dd[j] = diff * diff;
        }
      } else {
        for (int64_t j = 0; j < N; ++j) {
          const float diff = pc[j] - x;
          const float sq = diff * diff;
          dd[j] = dd[j] + sq;
        }
      }
    }
    float best = -std::numeric_limits<float>::infinity();
    int64_t arg = 0;
    for (int64_t j = 0; j < N; ++j) {
      const float m = dd[j] < dist[j] ? dd[j] : dist[j];
      dist[j] = m;
    }
    for (int64_t j = 0; j < N; ++j) {
      if (dist[j] > best) {
        best = dist[j];
        arg = j;
      }
    }
    cur = arg;
  }
}

at::Tensor fps(const at::Tensor& points_, int64_t n_samples, int64_t start) {
  // Farthest-point sampling of every batch row from `start` (`efem_viz.geometry.fps.farthest_point_sample`: the
  // same indices). Finite float32 points only (the caller checks); one loop per row instead of one kernel launch
  // per sample and component.
  TORCH_CHECK(points_.dim() == 3 && points_.scalar_type() == at::kFloat, "points must be (B, N, D) float32");
  TORCH_CHECK(points_.device().is_cpu(), "CPU tensors only");
  const int64_t B = points_.size(0), N = points_.size(1), D = points_.size(2);
  TORCH_CHECK(D >= 1, "points need at least one coordinate");
  TORCH_CHECK(n_samples >= 1 && n_samples <= N, "n_samples must be in [1, N]");
  TORCH_CHECK(start >= 0 && start < N, "start must be in [0, N)");
  const auto pts = points_.permute({0, 2, 1}).contiguous();  // (B, D, N)
  auto out = at::empty({B, n_samples}, points_.options().dtype(at::kLong));
  const float* pp = pts.data_ptr<float>();
  int64_t* po = out.data_ptr<int64_t>();
  at::parallel_for(0, B, 1, [&](int64_t begin, int64_t end) {
    std::vector<float> dist(N), dd(N);
    for (int64_t b = begin; b < end; ++b)
      fps_row(pp + b * D * N, D, N, N, n_samples, start, po + b * n_samples, dist.data(), dd.data());
  });
  return out;
}

// Scratch of one thread's k-NN rows.
struct KnnScratch {
  std::vector<float> d, bd;
  std::vector<int64_t> bi;
  std::vector<std::pair<float, int64_t>> queue;
  std::vector<int32_t> within;
  KnnScratch(int64_t Nr, int64_t k) : d(Nr), bd(k), bi(k), within(Nr) {}
};

// One query row of `knn_select`: g its Gram row (Nr entries), q its squared norm, r the reference rows' squared
// norms, fb the reference rows themselves ((Nr, D), or null: every tie takes torch's selection); o gets k indices.
void knn_row(const float* g, float q, const float* r, int64_t Nr, int64_t k, const float* fb, int64_t D, int64_t* o,
             KnnScratch& s) {
  std::vector<float>& d = s.d;
  std::vector<float>& bd = s.bd;
  std::vector<int64_t>& bi = s.bi;
  std::vector<int32_t>& within = s.within;
  bool nan = false;
  int64_t j0 = 0;
#ifdef __AVX512F__
  {  // the same two roundings per entry, 16 at a time
    const __m512 vq = _mm512_set1_ps(q);
    __mmask16 unord = 0;
    for (; j0 + kLanes <= Nr; j0 += kLanes) {
      const __m512 gv = _mm512_loadu_ps(g + j0);
      const __m512 dv = _mm512_add_ps(_mm512_sub_ps(vq, _mm512_add_ps(gv, gv)), _mm512_loadu_ps(r + j0));
      unord |= _mm512_cmp_ps_mask(dv, dv, _CMP_UNORD_Q);
      _mm512_storeu_ps(d.data() + j0, dv);
    }
    nan = unord != 0;
  }
#endif
  for (int64_t j = j0; j < Nr; ++j) {
    const float t = q - 2.0f * g[j];  // 2 g is exact: the eager (qq - 2 G) + rr, rounding for rounding
    d[j] = t + r[j];
    nan |= std::isnan(d[j]);
  }
  if (nan) {
    topk_smallest_like_torch(d.data(), Nr, k, o, s.queue);
    return;
  }
  bool done = false;
#ifdef __AVX512F__
  if (k == kLanes) {  // the usual k: the sorted buffer is one register pair
    done = select16(d.data(), Nr, bd.data(), bi.data());
  }
#endif
  if (!done) {
    int64_t n = 0;  // filled entries of the buffer, ascending
    for (int64_t j = 0; j < Nr; ++j) {  // insertion: equal distances after the ones already there
      const float v = d[j];
      if (n == k && !(v < bd[k - 1])) continue;
      int64_t pos = n < k ? n++ : k - 1;
      while (pos > 0 && v < bd[pos - 1]) {
        bd[pos] = bd[pos - 1];
        bi[pos] = bi[pos - 1];
        --pos;
      }
      bd[pos] = v;
      bi[pos] = j;
    }
  }
  bool tie = false;
  for (int64_t i = 0; i + 1 < k && !tie; ++i) tie = bd[i] == bd[i + 1];
  if (!tie) {  // the k-th distance unique in the row too?
    const float last = bd[k - 1];
    int64_t equal = 0, jj = 0;
#ifdef __AVX512F__
    const __m512 vl = _mm512_set1_ps(last);
    for (; jj + kLanes <= Nr; jj += kLanes)
      equal += __builtin_popcount(_mm512_cmp_ps_mask(_mm512_loadu_ps(d.data() + jj), vl, _CMP_EQ_OQ));
#endif
    for (; jj < Nr; ++jj) equal += d[jj] == last;
    tie = equal != 1;
  }
  if (tie && fb != nullptr) {  // only duplicates tied? every entry at most the k-th distance, grouped by value
    const float last = bd[k - 1];
    int64_t m = 0, jj = 0;
#ifdef __AVX512F__
    const __m512 vl = _mm512_set1_ps(last);
    const __m512i lane = _mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    for (; jj + kLanes <= Nr; jj += kLanes) {
      const __mmask16 le = _mm512_cmp_ps_mask(_mm512_loadu_ps(d.data() + jj), vl, _CMP_LE_OQ);
      _mm512_mask_compressstoreu_epi32(within.data() + m, le,
                                       _mm512_add_epi32(lane, _mm512_set1_epi32(static_cast<int32_t>(jj))));
      m += __builtin_popcount(le);
    }
#endif
    for (; jj < Nr; ++jj)
      if (d[jj] <= last) within[m++] = static_cast<int32_t>(jj);
    bool same = true;
    for (int64_t i = 1; i < m && same; ++i) {  // each equal to the first earlier entry of its value
      const float v = d[within[i]];
      for (int64_t e = 0; e < i; ++e) {
        if (d[within[e]] != v) continue;
        same = std::memcmp(fb + within[i] * D, fb + within[e] * D, sizeof(float) * D) == 0;
        break;
      }
    }
    tie = !same;
  }
  if (tie) {
    topk_smallest_like_torch(d.data(), Nr, k, o, s.queue);
  } else {
    std::copy(bi.begin(), bi.end(), o);
  }
}

// The squared norms and k of a k-NN call on B batches of Nq query and Nr reference rows.
void check_knn_norms(const at::Tensor& qq, const at::Tensor& rr, int64_t B, int64_t Nq, int64_t Nr, int64_t k) {
  TORCH_CHECK(qq.dim() == 2 && qq.size(0) == B && qq.size(1) == Nq && qq.scalar_type() == at::kFloat,
              "qq must be (B, Nq) float32");
  TORCH_CHECK(rr.dim() == 2 && rr.size(0) == B && rr.size(1) == Nr && rr.scalar_type() == at::kFloat,
              "rr must be (B, Nr) float32");
  TORCH_CHECK(k >= 1 && k <= Nr, "k must be in [1, Nr]");
  TORCH_CHECK(Nr <= std::numeric_limits<int32_t>::max(), "at most 2^31 - 1 reference rows");
}

at::Tensor knn_select(const at::Tensor& gram_, const at::Tensor& qq_, const at::Tensor& rr_, int64_t k,
                      const std::optional<at::Tensor>& ref_) {
  // The k nearest reference rows of every query row from the Gram matrix G = q r^T and the squared norms, with
  // the answer of the eager `((qq_i - 2 G_ij) + rr_j).topk(k, largest=False)`: the distances rounded as it
  // rounds them, the k smallest found by one insertion pass per row (no sort of the row); a row with equal
  // distances among or at the edge of its k (duplicate points, mostly) or a NaN takes torch's own selection, so
  // ties come out in torch's order too. Given the reference rows (`ref`, (B, Nr, D)), a row whose equal distances
  // all belong to identical reference rows (duplicates: every gather of them gives the same values in any order)
  // keeps the insertion pass's answer (equal distances by ascending index), as cheap as a row without ties.
  TORCH_CHECK(gram_.dim() == 3 && gram_.scalar_type() == at::kFloat, "gram must be (B, Nq, Nr) float32");
  TORCH_CHECK(gram_.device().is_cpu(), "CPU tensors only");
  const int64_t B = gram_.size(0), Nq = gram_.size(1), Nr = gram_.size(2);
  check_knn_norms(qq_, rr_, B, Nq, Nr, k);
  const auto gram = gram_.contiguous(), qq = qq_.contiguous(), rr = rr_.contiguous();
  at::Tensor ref;
  int64_t D = 0;
  if (ref_.has_value()) {
    TORCH_CHECK(ref_->dim() == 3 && ref_->size(0) == B && ref_->size(1) == Nr && ref_->scalar_type() == at::kFloat,
                "ref must be (B, Nr, D) float32");
    ref = ref_->contiguous();
    D = ref.size(2);
  }
  const float* pf = D > 0 ? ref.data_ptr<float>() : nullptr;
  auto out = at::empty({B, Nq, k}, gram.options().dtype(at::kLong));
  if (out.numel() == 0) return out;
  const float* pg = gram.data_ptr<float>();
  const float* pq = qq.data_ptr<float>();
  const float* pr = rr.data_ptr<float>();
  int64_t* po = out.data_ptr<int64_t>();
  at::parallel_for(0, B * Nq, 16, [&](int64_t begin, int64_t end) {
    KnnScratch s(Nr, k);
    for (int64_t row = begin; row < end; ++row) {
      const int64_t b = row / Nq;
      knn_row(pg + row * Nr, pq[row], pr + b * Nr, Nr, k, D > 0 ? pf + b * Nr * D : nullptr, D, po + row * k, s);
    }
  });
  return out;
}

constexpr int64_t kKnnSlab = 64;  // query rows per Gram slab: 64 x Nr floats stay in L2 (256 KB at Nr = 1024)

at::Tensor knn(const at::Tensor& q_, const at::Tensor& r_, const at::Tensor& qq_, const at::Tensor& rr_, int64_t k) {
  // `knn_select(q @ r^T, qq, rr, k, r)` without the (B, Nq, Nr) Gram matrix in memory: each slab of 64 query rows
  // gets its Gram rows from the CPU GEMM (the entries of the batched product, bit for bit: the same dot products
  // in the same order) into a buffer that stays in cache, and the rows are selected from there.
  TORCH_CHECK(q_.dim() == 3 && r_.dim() == 3 && q_.size(0) == r_.size(0) && q_.size(2) == r_.size(2) &&
              q_.scalar_type() == at::kFloat && r_.scalar_type() == at::kFloat,
              "q (B, Nq, D) and r (B, Nr, D) must be float32 and agree");
  TORCH_CHECK(q_.device().is_cpu() && r_.device().is_cpu(), "CPU tensors only");
  const int64_t B = q_.size(0), Nq = q_.size(1), Nr = r_.size(1), D = q_.size(2);
  check_knn_norms(qq_, rr_, B, Nq, Nr, k);
  const auto q = q_.contiguous(), r = r_.contiguous(), qq = qq_.contiguous(), rr = rr_.contiguous();
  auto out = at::empty({B, Nq, k}, q.options().dtype(at::kLong));
  if (out.numel() == 0) return out;
  const float* pf = D > 0 ? r.data_ptr<float>() : nullptr;
  const float* pq = qq.data_ptr<float>();
  const float* pr = rr.data_ptr<float>();
  int64_t* po = out.data_ptr<int64_t>();
  const int64_t slabs = (Nq + kKnnSlab - 1) / kKnnSlab;
  at::parallel_for(0, B * slabs, 1, [&](int64_t begin, int64_t end) {
    KnnScratch s(Nr, k);
    auto gram = at::empty({kKnnSlab, Nr}, q.options());
    for (int64_t t = begin; t < end; ++t) {
      const int64_t b = t / slabs, s0 = (t % slabs) * kKnnSlab, n = std::min(kKnnSlab, Nq - s0);
      auto g = gram.narrow(0, 0, n);
      at::mm_out(g, q[b].narrow(0, s0, n), r[b].t());
      const float* pg = g.data_ptr<float>();
      for (int64_t i = 0; i < n; ++i) {
        const int64_t row = b * Nq + s0 + i;
        knn_row(pg + i * Nr, pq[row], pr + b * Nr, Nr, k, pf != nullptr ? pf + b * Nr * D : nullptr, D,
                po + row * k, s);
      }
    }
  });
  return out;
}

inline void relu_rows(const float* x, float* out, int64_t n) {
  for (int64_t j = 0; j < n; ++j) out[j] = x[j] > 0.0f ? x[j] : 0.0f;
}

// float -> bfloat16 bits, rounded to nearest even (c10::BFloat16's rounding, NaN kept a NaN): plain integer
// arithmetic
inline uint16_t to_bf16(float v) {
  uint32_t u;
  std::memcpy(&u, &v, sizeof u);
  if ((u & 0x7fffffffu) > 0x7f800000u) return 0x7fc0;
  return static_cast<uint16_t>((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

// The row loops of the bf16 decoder pass, 16 lanes at a time where the build has AVX-512 (the same rounding as
// to_bf16, which does the tail); the scalar loops are the reference.
#ifdef __AVX512F__
inline __m256i to_bf16x16(__m512 v) {
  const __m512i u = _mm512_castps_si512(v);
  const __m512i lsb = _mm512_and_si512(_mm512_srli_epi32(u, 16), _mm512_set1_epi32(1));
  __m512i r = _mm512_srli_epi32(_mm512_add_epi32(_mm512_add_epi32(u, _mm512_set1_epi32(0x7fff)), lsb), 16);
  r = _mm512_mask_mov_epi32(r, _mm512_cmp_ps_mask(v, v, _CMP_UNORD_Q), _mm512_set1_epi32(0x7fc0));
  return _mm512_cvtepi32_epi16(r);
}

inline void store16(uint16_t* p, __m256i v) { _mm256_storeu_si256(reinterpret_cast<__m256i*>(p), v); }
#endif

// l = bf16(x)
inline void bf16_row(const float* x, uint16_t* l, int64_t n) {
  int64_t j = 0;
#ifdef __AVX512F__
  for (; j + kLanes <= n; j += kLanes) store16(l + j, to_bf16x16(_mm512_loadu_ps(x + j)));
#endif
  for (; j < n; ++j) l[j] = to_bf16(x[j]);
}

// h = M q + a_q |q| + bias (m: the five rows of one latent, each H wide), a = relu(h); the same operations in the
// same order in both branches (the q1 product, fused multiply-adds of q0, q2 and |q|, then the bias: the rounding
// GCC gave the plain expression, so the pass's results did not change when it was written out)
inline void first_row(const float* m, float q0, float q1, float q2, float qn, float* h, float* a, int64_t H) {
  int64_t j = 0;
#ifdef __AVX512F__
  const __m512 v0 = _mm512_set1_ps(q0), v1 = _mm512_set1_ps(q1), v2 = _mm512_set1_ps(q2),
               vn = _mm512_set1_ps(qn), zero = _mm512_setzero_ps();
  for (; j + kLanes <= H; j += kLanes) {
    __m512 v = _mm512_mul_ps(_mm512_loadu_ps(m + H + j), v1);
    v = _mm512_fmadd_ps(_mm512_loadu_ps(m + j), v0, v);
    v = _mm512_fmadd_ps(_mm512_loadu_ps(m + 2 * H + j), v2, v);
    v = _mm512_fmadd_ps(_mm512_loadu_ps(m + 3 * H + j), vn, v);
    v = _mm512_add_ps(v, _mm512_loadu_ps(m + 4 * H + j));
    _mm512_storeu_ps(h + j, v);
    _mm512_storeu_ps(a + j, _mm512_max_ps(v, zero));
  }
#endif
  for (; j < H; ++j) {
    float v = m[H + j] * q1;
#ifdef __FMA__
    v = std::fma(m[j], q0, v);
    v = std::fma(m[2 * H + j], q2, v);
    v = std::fma(m[3 * H + j], qn, v);
#else  // a build without FMA instructions (below AVX2): plain products, not a library call per unit
    v = v + m[j] * q0;
    v = v + m[2 * H + j] * q2;
    v = v + m[3 * H + j] * qn;
#endif
    v = v + m[4 * H + j];
    h[j] = v;
    a[j] = v > 0.0f ? v : 0.0f;
  }
}

// g = w where h > 0, else 0 (the output layer's gradient through the last ReLU)
inline void pass_row(const float* h, const float* w, float* g, int64_t H) {
  int64_t j = 0;
#ifdef __AVX512F__
  for (; j + kLanes <= H; j += kLanes) {
    const __mmask16 k = _mm512_cmp_ps_mask(_mm512_loadu_ps(h + j), _mm512_setzero_ps(), _CMP_GT_OQ);
    _mm512_storeu_ps(g + j, _mm512_maskz_mov_ps(k, _mm512_loadu_ps(w + j)));
  }
#endif
  for (; j < H; ++j) g[j] = h[j] > 0.0f ? w[j] : 0.0f;
}

// The epilogues between the bf16 pass's products (c: a product, float32), each writing the next product's bf16
// operand l.
// u = u + b (u holds the product); l = bf16(relu(u))
inline void inner_rowf(float* u, const float* b, uint16_t* l, int64_t n) {
  int64_t j = 0;
#ifdef __AVX512F__
  const __m512 zero = _mm512_setzero_ps();
  for (; j + kLanes <= n; j += kLanes) {
    const __m512 v = _mm512_add_ps(_mm512_loadu_ps(u + j), _mm512_loadu_ps(b + j));
    _mm512_storeu_ps(u + j, v);
    store16(l + j, to_bf16x16(_mm512_max_ps(v, zero)));
  }
#endif
  for (; j < n; ++j) {
    const float v = u[j] + b[j];
    u[j] = v;
    l[j] = to_bf16(v > 0.0f ? v : 0.0f);
  }
}

// h' = h + c + b; a = relu(h'); l = bf16(a)
inline void stream_rowf(const float* h, const float* c, const float* b, float* hn, float* a, uint16_t* l,
                        int64_t n) {
  int64_t j = 0;
#ifdef __AVX512F__
  const __m512 zero = _mm512_setzero_ps();
  for (; j + kLanes <= n; j += kLanes) {
    const __m512 v = _mm512_add_ps(_mm512_add_ps(_mm512_loadu_ps(h + j), _mm512_loadu_ps(c + j)),
                                   _mm512_loadu_ps(b + j));
    const __m512 y = _mm512_max_ps(v, zero);
    _mm512_storeu_ps(hn + j, v);
    _mm512_storeu_ps(a + j, y);
    store16(l + j, to_bf16x16(y));
  }
#endif
  for (; j < n; ++j) {
    const float v = h[j] + c[j] + b[j];
    const float y = v > 0.0f ? v : 0.0f;
    hn[j] = v;
    a[j] = y;
    l[j] = to_bf16(y);
  }
}

// l = bf16(c) where u > 0, else 0
inline void mask_rowf(const float* u, const float* c, uint16_t* l, int64_t n) {
  int64_t j = 0;
#ifdef __AVX512F__
  for (; j + kLanes <= n; j += kLanes) {
    const __mmask16 k = _mm512_cmp_ps_mask(_mm512_loadu_ps(u + j), _mm512_setzero_ps(), _CMP_GT_OQ);
    store16(l + j, to_bf16x16(_mm512_maskz_mov_ps(k, _mm512_loadu_ps(c + j))));
  }
#endif
  for (; j < n; ++j) l[j] = to_bf16(u[j] > 0.0f ? c[j] : 0.0f);
}

// g += c where h > 0
inline void grad_rowf(const float* h, const float* c, float* g, int64_t n) {
  int64_t j = 0;
#ifdef __AVX512F__
  for (; j + kLanes <= n; j += kLanes) {
    const __mmask16 k = _mm512_cmp_ps_mask(_mm512_loadu_ps(h + j), _mm512_setzero_ps(), _CMP_GT_OQ);
    const __m512 gv = _mm512_loadu_ps(g + j);
    _mm512_storeu_ps(g + j, _mm512_mask_add_ps(gv, k, gv, _mm512_loadu_ps(c + j)));
  }
#endif
  for (; j < n; ++j) g[j] += h[j] > 0.0f ? c[j] : 0.0f;
}

// The hidden products of the bf16 pass: C (m x H, float32) = L (m x H, bf16 bits) B, B an (H x H) float32 matrix
// whose entries are rounded to bf16 once; bf16 operands, float32 accumulation and results. Where oneDNN's bf16
// micro-kernel has a packed layout (AMX), B is packed once in column panels of kPanel (its packing takes no wider
// ones) and the micro-kernel runs per panel; elsewhere torch's CPU BLAS multiplies the plain bf16 B (the bf16 GEMM
// with float32 results of the BLAS library torch was built with; slow on CPUs without bf16 hardware).
struct Bf16Products {
  static constexpr int64_t kPanel = 32;
  bool vnni = false;
  int64_t H = 0;
  std::vector<at::Tensor> mats;  // bf16: packed panels (vnni) or row-major (H x H)

  Bf16Products(const std::vector<at::Tensor>& src, int64_t h) : H(h) {
    vnni = !src.empty() && H % kPanel == 0 && at::native::cpublas::could_pack(at::kBFloat16);
    for (const auto& b : src) {
      auto bb = b.contiguous().to(at::kBFloat16);
      if (vnni) {
        auto out = at::empty({H * H}, bb.options());
        for (int64_t c = 0; c < H; c += kPanel)
          at::native::cpublas::pack(H, kPanel, H, kPanel, at::kBFloat16, at::kBFloat16,
                                    bb.data_ptr<at::BFloat16>() + c, out.data_ptr<at::BFloat16>() + c * H);
        bb = out;
      }
      mats.push_back(bb);
    }
  }

  // C = L B_i for m rows
  void run(int64_t i, const uint16_t* l, int64_t m, float* c) const {
    if (m == 0) return;
    const auto* a = reinterpret_cast<const at::BFloat16*>(l);
    const at::BFloat16* b = mats[i].data_ptr<at::BFloat16>();
    if (!vnni) {
      at::native::cpublas::brgemm(m, H, H, H, H, H, false, a, b, c, false);
      return;
    }
    for (int64_t p = 0; p < H; p += kPanel)
      at::native::cpublas::brgemm(m, kPanel, H, H, kPanel, H, false, a, b + p * H, c + p, true);
  }

  void release() const {
    if (vnni) at::native::cpublas::brgemm_release(true);
  }
};

// The serial sums of several rows side by side: each row keeps its own order of additions (the rounding of a
// loop over one row) while the rows' chains overlap instead of waiting on one another.
constexpr int64_t kRowGroup = 8;

// sdf_r = w_out . a_r + b_out for n rows of width H
inline void output_rows(const float* a, const float* w, float b, float* out, int64_t n, int64_t H) {
  int64_t r = 0;
  for (; r + kRowGroup <= n; r += kRowGroup) {
    float acc[kRowGroup] = {};
    for (int64_t j = 0; j < H; ++j)
      for (int64_t k = 0; k < kRowGroup; ++k) acc[k] += a[(r + k) * H + j] * w[j];
    for (int64_t k = 0; k < kRowGroup; ++k) out[r + k] = acc[k] + b;
  }
  for (; r < n; ++r) {
    const float* ar = a + r * H;
    float acc = 0.0f;
    for (int64_t j = 0; j < H; ++j) acc += ar[j] * w[j];
    out[r] = acc + b;
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> decoder_band(
    const at::Tensor& q_, const at::Tensor& mt_, at::TensorList w0, at::TensorList b0, at::TensorList w1,
    at::TensorList b1, const at::Tensor& w_out_, double b_out, double within, bool use_qnorm, int64_t tile,
    bool bf16) {
  // The SDF decoder's inference pass (efem_viz/prior/decoder.py, `SDFDecoder.sdf_and_band_grad` is the same math)
  // over tiles of rows whose activations stay in cache: the first layer h0 = M q + a_q |q| + bias, the
  // pre-activation residual blocks h + W1 relu(W0 relu(h) + b0) + b1 and sdf = w_out . relu(h) + b_out, with bias,
  // ReLU and residual fused into one pass per layer between the matrix products; then, for the rows with
  // |sdf| <= within (none when within < 0), the input gradient back-propagated by hand through the kept ReLU masks
  // (a unit passes where its pre-activation > 0, as autograd's relu backward). q (B, Q, 3); mt (B, 5, H): the rows
  // of M^T, a_q and the bias of each latent; w0/w1 (H, H) as nn.Linear stores them, b0/b1 (H); w_out (H).
  // Returns sdf (B, Q), dq (B, Q, 3) (zeros outside the band) and band (B, Q) bool.
  // bf16: the hidden matrix products take bfloat16 operands (activations rounded to nearest even, weights rounded
  // once) and give float32 products (Bf16Products); the first layer, biases, ReLU masks, the residual stream, the
  // output layer and the gradient's sums stay float32.
  TORCH_CHECK(q_.dim() == 3 && q_.size(2) == 3 && q_.scalar_type() == at::kFloat, "q must be (B, Q, 3) float32");
  TORCH_CHECK(mt_.dim() == 3 && mt_.size(0) == q_.size(0) && mt_.size(1) == 5 && mt_.scalar_type() == at::kFloat,
              "mt must be (B, 5, H) float32");
  const int64_t nb = static_cast<int64_t>(w0.size());
  TORCH_CHECK(static_cast<int64_t>(b0.size()) == nb && static_cast<int64_t>(w1.size()) == nb &&
              static_cast<int64_t>(b1.size()) == nb, "one w0, b0, w1, b1 per block");
  const int64_t B = q_.size(0), Q = q_.size(1), H = mt_.size(2), N = B * Q;
  for (int64_t i = 0; i < nb; ++i) {
    for (const at::Tensor* w : {&w0[i], &w1[i]})
      TORCH_CHECK(w->dim() == 2 && w->size(0) == H && w->size(1) == H && w->scalar_type() == at::kFloat,
                  "block weights must be (H, H) float32");
    for (const at::Tensor* b : {&b0[i], &b1[i]})
      TORCH_CHECK(b->dim() == 1 && b->size(0) == H && b->scalar_type() == at::kFloat, "block biases must be (H,)");
  }
  TORCH_CHECK(w_out_.numel() == H && w_out_.scalar_type() == at::kFloat, "w_out must hold H float32");
  TORCH_CHECK(q_.device().is_cpu() && mt_.device().is_cpu(), "CPU tensors only");
  TORCH_CHECK(tile >= 1, "tile must be positive");
  const auto q = q_.detach().contiguous(), mt = mt_.detach().contiguous();
  const auto w_out = w_out_.detach().contiguous().view({H});
  std::vector<at::Tensor> w0c, w1c, w0t, w1t, b0c, b1c, mats;
  for (int64_t i = 0; i < nb; ++i) {
    // detached: the worker threads of parallel_for do not inherit the caller's no-grad mode, and the out= products
    // refuse tensors that require grad
    w0c.push_back(w0[i].detach().contiguous());
    w1c.push_back(w1[i].detach().contiguous());
    w0t.push_back(w0c.back().t());
    w1t.push_back(w1c.back().t());
    b0c.push_back(b0[i].detach().contiguous());
    b1c.push_back(b1[i].detach().contiguous());
    if (bf16) {  // per block: the forward's W0^T, W1^T, the backward's W1, W0 (products 4 i .. 4 i + 3)
      mats.push_back(w0t.back());
      mats.push_back(w1t.back());
      mats.push_back(w1c.back());
      mats.push_back(w0c.back());
    }
  }
  const Bf16Products prod(mats, H);
  auto sdf = at::empty({B, Q}, q.options());
  auto dq = at::zeros({B, Q, 3}, q.options());
  auto band = at::zeros({B, Q}, q.options().dtype(at::kBool));
  if (N == 0) return {sdf, dq, band};
  const float* pq = q.data_ptr<float>();
  const float* pm = mt.data_ptr<float>();
  const float* pw = w_out.data_ptr<float>();
  float* ps = sdf.data_ptr<float>();
  float* pd = dq.data_ptr<float>();
  bool* pb = band.data_ptr<bool>();
  const float bo = static_cast<float>(b_out), lim = static_cast<float>(within);
  const int64_t T = std::min(tile, N), n_tiles = (N + T - 1) / T;
  at::parallel_for(0, n_tiles, 1, [&](int64_t t_begin, int64_t t_end) {
    const auto opt = q.options();
    std::vector<at::Tensor> hs, us;  // the stream h_i (nb + 1) and the blocks' inner pre-activations u_i (nb)
    for (int64_t i = 0; i <= nb; ++i) hs.push_back(at::empty({T, H}, opt));
    for (int64_t i = 0; i < nb; ++i) us.push_back(at::empty({T, H}, opt));
    auto act = at::empty({T, H}, opt), g = at::empty({T, H}, opt), tmp = at::empty({T, H}, opt);
    // bf16: a product's left operand (bf16 bits)
    auto lb = bf16 ? at::empty({T, H}, opt.dtype(at::kBFloat16)) : at::Tensor();
    uint16_t* lp = bf16 ? reinterpret_cast<uint16_t*>(lb.data_ptr<at::BFloat16>()) : nullptr;
    float* cp = tmp.data_ptr<float>();
    std::vector<int64_t> sel;
    for (int64_t t = t_begin; t < t_end; ++t) {
      const int64_t s = t * T, n = std::min(T, N - s);
      float* h0 = hs[0].data_ptr<float>();
      float* a = act.data_ptr<float>();
      for (int64_t r = 0; r < n; ++r) {  // first layer, and its ReLU for the first block
        const int64_t row = s + r;
        const float* m = pm + (row / Q) * 5 * H;
        const float q0 = pq[row * 3], q1 = pq[row * 3 + 1], q2 = pq[row * 3 + 2];
        const float qn = use_qnorm ? std::sqrt(std::max(q0 * q0 + q1 * q1 + q2 * q2, 1e-24f)) : 0.0f;
        float* ar = a + r * H;
        first_row(m, q0, q1, q2, qn, h0 + r * H, ar, H);
        if (bf16) bf16_row(ar, lp + r * H, H);
      }
      auto a_n = act.narrow(0, 0, n);
      for (int64_t i = 0; bf16 && i < nb; ++i) {  // the blocks with bf16 operands
        float* up = us[i].data_ptr<float>();
        prod.run(4 * i, lp, n, up);
        const float* bz = b0c[i].data_ptr<float>();
        for (int64_t r = 0; r < n * H; r += H) inner_rowf(up + r, bz, lp + r, H);
        prod.run(4 * i + 1, lp, n, cp);
        const float* hp = hs[i].data_ptr<float>();
        float* hn = hs[i + 1].data_ptr<float>();
        const float* bb = b1c[i].data_ptr<float>();
        for (int64_t r = 0; r < n * H; r += H) stream_rowf(hp + r, cp + r, bb, hn + r, a + r, lp + r, H);
      }
      for (int64_t i = 0; !bf16 && i < nb; ++i) {
        auto u = us[i].narrow(0, 0, n);
        at::addmm_out(u, b0c[i], a_n, w0t[i]);
        relu_rows(u.data_ptr<float>(), a, n * H);
        auto h_next = hs[i + 1].narrow(0, 0, n);
        at::addmm_out(h_next, hs[i].narrow(0, 0, n), a_n, w1t[i]);
        float* hn = h_next.data_ptr<float>();
        const float* bb = b1c[i].data_ptr<float>();
        for (int64_t r = 0; r < n; ++r) {
          float* hr = hn + r * H;
          float* ar = a + r * H;
          for (int64_t j = 0; j < H; ++j) {
            const float v = hr[j] + bb[j];
            hr[j] = v;
            ar[j] = v > 0.0f ? v : 0.0f;
          }
        }
      }
      sel.clear();
      output_rows(a, pw, bo, ps + s, n, H);
      for (int64_t r = 0; r < n; ++r)
        if (std::abs(ps[s + r]) <= lim) sel.push_back(r);
      const int64_t nsel = static_cast<int64_t>(sel.size());
      if (nsel == 0) continue;
      float* gp = g.data_ptr<float>();
      const float* hl = hs[nb].data_ptr<float>();
      for (int64_t k = 0; k < nsel; ++k) pass_row(hl + sel[k] * H, pw, gp + k * H, H);
      auto g_n = g.narrow(0, 0, nsel), tmp_n = tmp.narrow(0, 0, nsel);
      for (int64_t i = nb - 1; bf16 && i >= 0; --i) {  // the same with bf16 operands
        bf16_row(gp, lp, nsel * H);
        prod.run(4 * i + 2, lp, nsel, cp);
        const float* up = us[i].data_ptr<float>();
        for (int64_t k = 0; k < nsel; ++k) mask_rowf(up + sel[k] * H, cp + k * H, lp + k * H, H);
        prod.run(4 * i + 3, lp, nsel, cp);
        const float* hp = hs[i].data_ptr<float>();
        for (int64_t k = 0; k < nsel; ++k) grad_rowf(hp + sel[k] * H, cp + k * H, gp + k * H, H);
      }
      for (int64_t i = nb - 1; !bf16 && i >= 0; --i) {
        at::mm_out(tmp_n, g_n, w1c[i]);  // d/d relu(u): g W1, then through u's mask
        const float* up = us[i].data_ptr<float>();
        for (int64_t k = 0; k < nsel; ++k) {
          const float* ur = up + sel[k] * H;
          float* tr = cp + k * H;
          for (int64_t j = 0; j < H; ++j) tr[j] = ur[j] > 0.0f ? tr[j] : 0.0f;
        }
        auto x_n = act.narrow(0, 0, nsel);  // act is free now: (t W0) through h_i's mask
        at::mm_out(x_n, tmp_n, w0c[i]);
        const float* hp = hs[i].data_ptr<float>();
        for (int64_t k = 0; k < nsel; ++k) {
          const float* hr = hp + sel[k] * H;
          const float* xr = a + k * H;
          float* gr = gp + k * H;
          for (int64_t j = 0; j < H; ++j) gr[j] += hr[j] > 0.0f ? xr[j] : 0.0f;
        }
      }
      for (int64_t k0 = 0; k0 < nsel; k0 += kRowGroup) {  // dsdf/dq = g [M, a_q] d[q, |q|]/dq
        const int64_t kn = std::min(kRowGroup, nsel - k0);
        float d[kRowGroup][4];
        const float *ms[kRowGroup], *gs[kRowGroup];
        for (int64_t k = 0; k < kRowGroup; ++k) {  // a short group repeats its last row (results unused)
          const int64_t kk = k0 + std::min(k, kn - 1);
          ms[k] = pm + ((s + sel[kk]) / Q) * 5 * H;
          gs[k] = gp + kk * H;
          d[k][0] = d[k][1] = d[k][2] = d[k][3] = 0.0f;
        }
        for (int64_t j = 0; j < H; ++j)
          for (int64_t k = 0; k < kRowGroup; ++k)
            for (int64_t c = 0; c < 4; ++c) d[k][c] += gs[k][j] * ms[k][c * H + j];
        for (int64_t k = k0; k < k0 + kn; ++k) {
          const int64_t row = s + sel[k];
          float d0 = d[k - k0][0], d1 = d[k - k0][1], d2 = d[k - k0][2], d3 = d[k - k0][3];
          const float q0 = pq[row * 3], q1 = pq[row * 3 + 1], q2 = pq[row * 3 + 2];
          if (use_qnorm) {
            const float qn = std::sqrt(std::max(q0 * q0 + q1 * q1 + q2 * q2, 1e-24f));
            d0 += d3 * q0 / qn;
            d1 += d3 * q1 / qn;
            d2 += d3 * q2 / qn;
          }
          pd[row * 3] = d0;
          pd[row * 3 + 1] = d1;
          pd[row * 3 + 2] = d2;
          pb[row] = true;
        }
      }
    }
    prod.release();
  });
  return {sdf, dq, band};
}

}  // namespace

TORCH_LIBRARY(efem_vn, m) {
  m.def("edge_mean(Tensor a, Tensor c, Tensor da, Tensor dc, Tensor nbr, float slope) -> Tensor", &edge_mean);
  m.def("edge_mean_backward(Tensor grad, Tensor a, Tensor c, Tensor da, Tensor dc, Tensor nbr, float slope) -> "
        "(Tensor, Tensor, Tensor, Tensor)", &edge_mean_backward);
  m.def("edge_act(Tensor a, Tensor c, Tensor da, Tensor dc, Tensor nbr, float slope) -> Tensor", &edge_act);
  m.def("edge_act_backward(Tensor grad, Tensor a, Tensor c, Tensor da, Tensor dc, Tensor nbr, float slope) -> "
        "(Tensor, Tensor, Tensor, Tensor)", &edge_act_backward);
  m.def("leaky(Tensor x, Tensor d, float slope) -> Tensor", &leaky);
  m.def("leaky_backward(Tensor grad, Tensor x, Tensor d, float slope) -> (Tensor, Tensor)", &leaky_backward);
  m.def("act_mean(Tensor x, Tensor d, float slope) -> Tensor", &act_mean);
  m.def("lin_act_mean(Tensor x, Tensor w, Tensor u, float slope) -> Tensor", &lin_act_mean);
  m.def("fps(Tensor points, int n_samples, int start) -> Tensor", &fps);
  m.def("knn_select(Tensor gram, Tensor qq, Tensor rr, int k, Tensor? ref=None) -> Tensor", &knn_select);
  m.def("knn(Tensor q, Tensor r, Tensor qq, Tensor rr, int k) -> Tensor", &knn);
  m.def("attention(Tensor av, Tensor cv, Tensor dav, Tensor dcv, Tensor ak, Tensor ck, Tensor dak, Tensor dck, "
        "Tensor q, Tensor nbr, float slope, int head_dim, float eps) -> Tensor", &attention);
  m.def("decoder_band(Tensor q, Tensor mt, Tensor[] w0, Tensor[] b0, Tensor[] w1, Tensor[] b1, Tensor w_out, "
        "float b_out, float within, bool use_qnorm, int tile, bool bf16=False) -> (Tensor, Tensor, Tensor)",
        &decoder_band);
}
