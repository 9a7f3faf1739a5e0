// Fused TensorVM (TensoRF vector-matrix) grid lookups on the CPU: nerfart_plugin/fields/fused_grid.py builds
// this file into a shared library and calls it through ctypes (no PyTorch headers: it builds in a few seconds).
//
// Per point n, level l (side r_l) and plane axis a (planes (x,y), (x,z), (y,z); lines z, y, x), component c:
//     out[n, l*3C + a*C + c] = bilinear(P_la[:, :, c], x_i, x_j) * linear(L_la[:, c], x_k)
// with coordinates in [-1, 1] mapped to [0, r-1] (align_corners=True) and zero padding, the same arithmetic as
// ATen's grid_sample (bilinear), so the result equals the grid_sample path up to float rounding.
// Layouts (channel-last, so that a corner's C components are contiguous): planes [3, r, r, C] (row: the second
// plane coordinate), lines [3, r, C]; points xn [N, 3] already clamped to [-1, 1].
//
// The backward scatters grad_out [N, 3LC] into the planes' and lines' gradients (same layouts). Threads own
// contiguous point ranges; each thread but the first accumulates into a private buffer, summed at the end.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <thread>
#include <vector>

namespace {

constexpr int kPlaneI[3] = {0, 0, 1};  // the plane's first coordinate (column, grid_sample's W)
constexpr int kPlaneJ[3] = {1, 2, 2};  // its second coordinate (row, grid_sample's H)
constexpr int kLine[3] = {2, 1, 0};    // the line's coordinate
constexpr int kMaxC = 256;             // components per level at most (encoding.n_components' limit)

template <typename T>
struct Lookup {  // one plane's bilinear corners and its line's linear pair: offsets (in elements) and weights
  int64_t p00, p01, p10, p11, l0, l1;
  T nw, ne, sw, se, ln, ls;
};

// Points are clamped to [-1, 1] by the caller; a NaN coordinate is the only thing left that would index
// outside the planes.
template <typename T>
inline bool finite_point(const T* p) {
  return !(std::isnan(p[0]) || std::isnan(p[1]) || std::isnan(p[2]));
}

// The corners of plane axis a at point p [3] on a level of side r, components C. A corner past the last cell
// (a coordinate of exactly 1) has weight 0; its offset is clamped to the last cell, which adds 0 x a finite value.
template <typename T>
inline Lookup<T> lookup(const T* p, int a, int64_t r, int C) {
  const T scale = T(r - 1) / T(2);
  const T ix = (p[kPlaneI[a]] + T(1)) * scale, iy = (p[kPlaneJ[a]] + T(1)) * scale, il = (p[kLine[a]] + T(1)) * scale;
  const T fx = std::floor(ix), fy = std::floor(iy), fl = std::floor(il);
  const int64_t x0 = int64_t(fx), y0 = int64_t(fy), z0 = int64_t(fl);
  const int64_t x1 = std::min(x0 + 1, r - 1), y1 = std::min(y0 + 1, r - 1), z1 = std::min(z0 + 1, r - 1);
  Lookup<T> k;
  k.p00 = (y0 * r + x0) * C; k.p01 = (y0 * r + x1) * C; k.p10 = (y1 * r + x0) * C; k.p11 = (y1 * r + x1) * C;
  k.l0 = z0 * C; k.l1 = z1 * C;
  k.nw = (fx + T(1) - ix) * (fy + T(1) - iy);
  k.ne = (ix - fx) * (fy + T(1) - iy);
  k.sw = (fx + T(1) - ix) * (iy - fy);
  k.se = (ix - fx) * (iy - fy);
  k.ln = fl + T(1) - il;
  k.ls = il - fl;
  return k;
}

template <typename T, int CC>
void forward_range(const T* __restrict xn, int64_t begin, int64_t end, int L, const int64_t* sides,
                   const T* const* planes, const T* const* lines, int Cr, T* __restrict out) {
  const int C = CC > 0 ? CC : Cr;
  const int64_t F = int64_t(3) * L * C;
  for (int64_t n = begin; n < end; ++n) {
    const T* p = xn + 3 * n;
    T* __restrict o = out + F * n;
    if (!finite_point(p)) {  // as grid_sample: every feature of a NaN point is NaN (no memory is read)
      for (int64_t f = 0; f < F; ++f) o[f] = std::numeric_limits<T>::quiet_NaN();
      continue;
    }
    for (int l = 0; l < L; ++l) {
      const int64_t r = sides[l];
      for (int a = 0; a < 3; ++a) {
        const Lookup<T> k = lookup(p, a, r, C);
        const T* __restrict P = planes[l] + a * r * r * C;
        const T* __restrict Li = lines[l] + a * r * C;
        T* __restrict oc = o + (l * 3 + a) * C;
        for (int c = 0; c < C; ++c) {
          const T pv = k.nw * P[k.p00 + c] + k.ne * P[k.p01 + c] + k.sw * P[k.p10 + c] + k.se * P[k.p11 + c];
          const T lv = k.ln * Li[k.l0 + c] + k.ls * Li[k.l1 + c];
          oc[c] = pv * lv;
        }
      }
    }
  }
}

// The backward goes plane by plane (level l, axis a) over the point range: one plane and its gradient are the
// working set of a pass, instead of all of them at once (the scatter is bound by cache misses otherwise).
template <typename T, int CC>
void backward_range(const T* __restrict xn, int64_t begin, int64_t end, int L, const int64_t* sides,
                    const T* const* planes, const T* const* lines, int Cr, const T* __restrict grad_out,
                    T* const* gplanes, T* const* glines) {
  const int C = CC > 0 ? CC : Cr;
  const int64_t F = int64_t(3) * L * C;
  for (int l = 0; l < L; ++l) {
    const int64_t r = sides[l];
    for (int a = 0; a < 3; ++a) {
      const int64_t poff = a * r * r * C, loff = a * r * C;
      const T* __restrict P = planes[l] + poff;
      const T* __restrict Li = lines[l] + loff;
      T* GP = gplanes[l] + poff;
      T* GL = glines[l] + loff;
      for (int64_t n = begin; n < end; ++n) {
        if (!finite_point(xn + 3 * n)) continue;  // as grid_sample: a NaN point scatters nothing
        const Lookup<T> k = lookup(xn + 3 * n, a, r, C);
        const T* __restrict gc = grad_out + F * n + (l * 3 + a) * C;
        T gp[kMaxC], gl[kMaxC];  // d loss / d (plane value), d loss / d (line value), per component
        for (int c = 0; c < C; ++c) {
          const T pv = k.nw * P[k.p00 + c] + k.ne * P[k.p01 + c] + k.sw * P[k.p10 + c] + k.se * P[k.p11 + c];
          const T lv = k.ln * Li[k.l0 + c] + k.ls * Li[k.l1 + c];
          gp[c] = gc[c] * lv;
          gl[c] = gc[c] * pv;
        }
        // one loop per corner: each is a plain vector update (corners may coincide at the grid's last cell)
        for (int c = 0; c < C; ++c) GP[k.p00 + c] += k.nw * gp[c];
        for (int c = 0; c < C; ++c) GP[k.p01 + c] += k.ne * gp[c];
        for (int c = 0; c < C; ++c) GP[k.p10 + c] += k.sw * gp[c];
        for (int c = 0; c < C; ++c) GP[k.p11 + c] += k.se * gp[c];
        for (int c = 0; c < C; ++c) GL[k.l0 + c] += k.ln * gl[c];
        for (int c = 0; c < C; ++c) GL[k.l1 + c] += k.ls * gl[c];
      }
    }
  }
}

template <typename Fn>
void parallel(int64_t n, int threads, int64_t min_per_thread, Fn fn) {
  const int64_t t = std::max<int64_t>(1, std::min<int64_t>(threads, n / std::max<int64_t>(1, min_per_thread)));
  if (t == 1) { fn(0, int64_t(0), n); return; }
  std::vector<std::thread> pool;
  const int64_t chunk = (n + t - 1) / t;
  for (int64_t i = 1; i < t; ++i) {
    const int64_t b = i * chunk, e = std::min(n, b + chunk);
    if (b < e) pool.emplace_back(fn, int(i), b, e);
  }
  fn(0, int64_t(0), std::min(n, chunk));
  for (auto& th : pool) th.join();
}

template <typename T, int CC>
void forward(const T* xn, int64_t N, int L, const int64_t* sides, const T* const* planes, const T* const* lines,
             int C, T* out, int threads) {
  parallel(N, threads, 2048, [&](int, int64_t b, int64_t e) {
    forward_range<T, CC>(xn, b, e, L, sides, planes, lines, C, out);
  });
}

template <typename T, int CC>
void backward(const T* xn, int64_t N, int L, const int64_t* sides, const T* const* planes, const T* const* lines,
              int C, const T* grad_out, T* const* gplanes, T* const* glines, int threads) {
  // sizes of each level's plane and line gradients, and their offsets in a thread's private buffer
  std::vector<int64_t> psz(L), lsz(L), poff(L), loff(L);
  int64_t total = 0;
  for (int l = 0; l < L; ++l) {
    psz[l] = 3 * sides[l] * sides[l] * C; lsz[l] = 3 * sides[l] * C;
    poff[l] = total; total += psz[l]; loff[l] = total; total += lsz[l];
  }
  const int64_t t = std::max<int64_t>(1, std::min<int64_t>(threads, N / 4096));
  std::vector<std::vector<T>> priv(t - 1);
  parallel(N, int(t), 4096, [&](int i, int64_t b, int64_t e) {
    if (i == 0) {
      backward_range<T, CC>(xn, b, e, L, sides, planes, lines, C, grad_out, gplanes, glines);
      return;
    }
    std::vector<T>& buf = priv[i - 1];
    buf.assign(total, T(0));
    std::vector<T*> gp(L), gl(L);
    for (int l = 0; l < L; ++l) { gp[l] = buf.data() + poff[l]; gl[l] = buf.data() + loff[l]; }
    backward_range<T, CC>(xn, b, e, L, sides, planes, lines, C, grad_out, gp.data(), gl.data());
  });
  // sum the private buffers into the outputs, each thread a slice of every level's planes and lines
  if (priv.empty()) return;
  parallel(total, int(t), 65536, [&](int, int64_t b, int64_t e) {
    for (int l = 0; l < L; ++l) {
      const int64_t pb = std::max(b, poff[l]) - poff[l], pe = std::min(e, poff[l] + psz[l]) - poff[l];
      const int64_t lb = std::max(b, loff[l]) - loff[l], le = std::min(e, loff[l] + lsz[l]) - loff[l];
      for (const auto& buf : priv) {
        if (buf.empty()) continue;  // a thread without points
        for (int64_t j = pb; j < pe; ++j) gplanes[l][j] += buf[poff[l] + j];
        for (int64_t j = lb; j < le; ++j) glines[l][j] += buf[loff[l] + j];
      }
    }
  });
}

template <typename T>
void forward_dispatch(const T* xn, int64_t N, int L, const int64_t* sides, const T* const* planes,
                      const T* const* lines, int C, T* out, int threads) {
  switch (C) {
    case 4: return forward<T, 4>(xn, N, L, sides, planes, lines, C, out, threads);
    case 8: return forward<T, 8>(xn, N, L, sides, planes, lines, C, out, threads);
    case 16: return forward<T, 16>(xn, N, L, sides, planes, lines, C, out, threads);
    default: return forward<T, 0>(xn, N, L, sides, planes, lines, C, out, threads);
  }
}

template <typename T>
void backward_dispatch(const T* xn, int64_t N, int L, const int64_t* sides, const T* const* planes,
                       const T* const* lines, int C, const T* grad_out, T* const* gplanes, T* const* glines,
                       int threads) {
  switch (C) {
    case 4: return backward<T, 4>(xn, N, L, sides, planes, lines, C, grad_out, gplanes, glines, threads);
    case 8: return backward<T, 8>(xn, N, L, sides, planes, lines, C, grad_out, gplanes, glines, threads);
    case 16: return backward<T, 16>(xn, N, L, sides, planes, lines, C, grad_out, gplanes, glines, threads);
    default: return backward<T, 0>(xn, N, L, sides, planes, lines, C, grad_out, gplanes, glines, threads);
  }
}

}  // namespace

extern "C" {
int tensorvm_abi_version() { return 1; }

void tensorvm_forward_f32(const float* xn, int64_t N, int L, const int64_t* sides, const float* const* planes,
                          const float* const* lines, int C, float* out, int threads) {
  forward_dispatch<float>(xn, N, L, sides, planes, lines, C, out, threads);
}
void tensorvm_forward_f64(const double* xn, int64_t N, int L, const int64_t* sides, const double* const* planes,
                          const double* const* lines, int C, double* out, int threads) {
  forward_dispatch<double>(xn, N, L, sides, planes, lines, C, out, threads);
}
void tensorvm_backward_f32(const float* xn, int64_t N, int L, const int64_t* sides, const float* const* planes,
                           const float* const* lines, int C, const float* grad_out, float* const* gplanes,
                           float* const* glines, int threads) {
  backward_dispatch<float>(xn, N, L, sides, planes, lines, C, grad_out, gplanes, glines, threads);
}
void tensorvm_backward_f64(const double* xn, int64_t N, int L, const int64_t* sides, const double* const* planes,
                           const double* const* lines, int C, const double* grad_out, double* const* gplanes,
                           double* const* glines, int threads) {
  backward_dispatch<double>(xn, N, L, sides, planes, lines, C, grad_out, gplanes, glines, threads);
}
}
