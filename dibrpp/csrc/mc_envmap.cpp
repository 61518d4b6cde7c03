// Fused Monte-Carlo shading of packed pixels under an equirectangular env map (CPU, float32).
//
// One pass per chunk of samples: BRDF or env-map direction sampling, BRDF value and pdf, bilinear radiance,
// MIS weight (balance heuristic), summed over the samples of each pixel. The backward scatters
// grad_out x f x weight into the four texels of each sample's bilinear look-up: the gradient w.r.t. the
// env map alone (the Python caller, dibrpp/shading.py, uses this path only when nothing else needs one).
// Pixels are shaded 8 at a time by loops the compiler vectorises (see "lanes" below).
//
// Every formula mirrors the PyTorch code it replaces, operation for operation, with the same uniforms, so
// that values agree to float rounding (the transcendental functions are polynomials within 2 ulp of libm):
// dibrpp/brdf.py (ShadingPoint.sample_directions, eval, pdf, fresnel, diffuse_weight,
// specular_selection_probability), dibrpp/lights.py (EnvMap._bilinear, sample, pdf) and dibrpp/shading.py
// (_MCPlan.terms). Change one, change both: tests/dibrpp/test_mc_native.py compares them.
#include <ATen/Parallel.h>
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

constexpr float kPi = 3.14159265358979323846f;
constexpr double kPiD = 3.14159265358979323846;

struct Vec3 {
  float x, y, z;
};
inline Vec3 operator*(float s, Vec3 a) { return {s * a.x, s * a.y, s * a.z}; }
inline float dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline float clampf(float x, float lo, float hi) { return std::min(std::max(x, lo), hi); }

// Inputs shared by every pixel, as raw pointers (contiguous tensors).
struct Scene {
  const float *normal, *view, *albedo, *alpha, *metallic, *specular;
  const int64_t* batch;
  const float* image;  // (Bi, H, W, 3)
  int64_t bi, h, w;
  const float* rot;  // (Br, 3, 3) world -> light, or nullptr
  int64_t br;
  const double *cdf, *row_cdf, *tex_pdf, *cos_edges;  // sampling tables (Bt, ...), or nullptr without MIS
  int64_t bt;
  bool smith, mis;
  int64_t n_brdf, n_light;
};

// --- BRDF (dibrpp/brdf.py) -------------------------------------------------------------------------------

inline float fresnel_dielectric(float cos_i, float eta) {
  float c = clampf(cos_i, 0.f, 1.f);
  float g2 = eta * eta - 1 + c * c;
  float g = std::sqrt(std::max(g2, 0.f));
  float a = (g - c) / std::max(g + c, 1e-12f);
  float b = (c * (g + c) - 1) / (c * (g - c) + 1);
  return g2 > 0 ? 0.5f * a * a * (1 + b * b) : 1.f;
}

inline float smith_lambda(float cos, float alpha) {
  float c = clampf(cos, 1e-6f, 1.f);
  float c2 = c * c;
  float tan2 = (1 - c2) / c2;
  return 0.5f * (std::sqrt(1 + alpha * alpha * tan2) - 1);
}

inline float schlick_g1(float c, float alpha) { return c / (c * (1 - alpha) + alpha); }

inline float ggx_d(float n_dot_h, float alpha) {
  float a2 = alpha * alpha;
  float c = clampf(n_dot_h, 0.f, 1.f);
  float c2 = c * c;
  float t = c2 * (a2 - 1) + 1;
  return a2 / (kPi * (t * t));
}

// Per-pixel quantities of a ShadingPoint that do not depend on the light direction.
struct Pixel {
  Vec3 n, v, albedo, t, b;
  float alpha, metallic, eta, spec_on, p_spec;
  // hoisted out of the sample loop (the same operations, so the same values)
  float diffuse_over_pi[3], four_n_dot_v, view_geometry;  // a_d / pi; 4 (n.v); Smith lambda(n.v), or Schlick G1(n.v)
  bool dielectric;  // the dielectric Fresnel term is weighted by (1 - m) > 0 and specular > 0
};

Pixel make_pixel(const Scene& s, int64_t i) {  // the ShadingPoint of pixel i
  Pixel p;
  p.n = {s.normal[3 * i], s.normal[3 * i + 1], s.normal[3 * i + 2]};
  p.v = {s.view[3 * i], s.view[3 * i + 1], s.view[3 * i + 2]};
  p.albedo = {s.albedo[3 * i], s.albedo[3 * i + 1], s.albedo[3 * i + 2]};
  p.alpha = s.alpha[i];
  p.metallic = s.metallic[i];
  float specular = s.specular[i];
  float n_dot_v = clampf(dot(p.n, p.v), 1e-4f, 1.f);
  float f0 = clampf(0.04f * 2 * specular, 0.f, 0.999f);  // dielectric_f0: ((1.5 - 1) / (1.5 + 1))^2 = 0.04
  float sq = std::sqrt(clampf(f0, 1e-8f, 0.999f));
  p.eta = (1 + sq) / (1 - sq);
  p.spec_on = specular > 0 ? 1.f : 0.f;
  float f_d = fresnel_dielectric(n_dot_v, p.eta) * p.spec_on;
  float dw = (1 - p.metallic) * (1 - f_d);
  Vec3 diffuse_weight = dw * p.albedo;
  p.diffuse_over_pi[0] = diffuse_weight.x / kPi;
  p.diffuse_over_pi[1] = diffuse_weight.y / kPi;
  p.diffuse_over_pi[2] = diffuse_weight.z / kPi;
  p.four_n_dot_v = 4 * n_dot_v;
  p.dielectric = (1 - p.metallic) != 0 && p.spec_on != 0;
  float spec_w = (1 - p.metallic) * f0 * p.spec_on + p.metallic;
  float diff_w = (diffuse_weight.x + diffuse_weight.y + diffuse_weight.z) / 3;
  float prob = spec_w / std::max(spec_w + diff_w, 1e-8f);
  p.p_spec = (spec_w > 0 && diff_w > 0) ? clampf(prob, 0.25f, 0.9f) : prob;
  // tangent frame (Duff et al. 2017), as brdf._tangent_frame
  float sign = p.n.z >= 0 ? 1.f : -1.f;
  float a = -1.f / (sign + p.n.z);
  float bb = p.n.x * p.n.y * a;
  p.t = {1 + sign * (p.n.x * p.n.x) * a, sign * bb, -sign * p.n.x};
  p.b = {bb, sign + (p.n.y * p.n.y) * a, -p.n.y};
  p.view_geometry = s.smith ? smith_lambda(n_dot_v, p.alpha) : schlick_g1(clampf(n_dot_v, 0.f, 1.f), p.alpha);
  return p;
}

// --- env map (dibrpp/lights.py) ---------------------------------------------------------------------------

// The four texels (flat indices into image, without the channel) and weights of a bilinear look-up.
struct Taps {
  int64_t idx[4];
  float wx0, wx1, wy0, wy1;
};

Taps bilinear_taps(const Scene& s, int64_t img, float u, float v) {
  float x = u * s.w - 0.5f, y = v * s.h - 0.5f;
  float x0f = std::floor(x), y0f = std::floor(y);
  float fx = x - x0f, fy = y - y0f;
  int64_t x0 = static_cast<int64_t>(x0f) % s.w;
  if (x0 < 0) x0 += s.w;
  int64_t x1 = (x0 + 1) % s.w;
  int64_t y0 = static_cast<int64_t>(y0f);
  int64_t base = (s.bi == 1 ? 0 : img) * s.h * s.w;
  int64_t r0 = base + std::min(std::max(y0, int64_t(0)), s.h - 1) * s.w;
  int64_t r1 = base + std::min(std::max(y0 + 1, int64_t(0)), s.h - 1) * s.w;
  return {{r0 + x0, r0 + x1, r1 + x0, r1 + x1}, 1 - fx, fx, 1 - fy, fy};
}

float texel_pdf(const Scene& s, int64_t img, float u, float v) {
  int64_t col = std::min(std::max(static_cast<int64_t>(u * s.w), int64_t(0)), s.w - 1);
  int64_t row = std::min(std::max(static_cast<int64_t>(v * s.h), int64_t(0)), s.h - 1);
  return static_cast<float>(s.tex_pdf[(s.bt == 1 ? 0 : img) * s.h * s.w + row * s.w + col]);
}

// Largest i in [0, n) with a[i] <= x for ascending a (searchsorted(right=True) - 1), -1 if none. Branchless
// (conditional moves): the random search paths of std::upper_bound mispredict at every level.
inline int64_t last_not_above(const double* a, int64_t n, double x) {
  const double* base = a;
  while (n > 1) {
    int64_t half = n / 2;
    base = base[half] <= x ? base + half : base;
    n -= half;
  }
  return static_cast<int64_t>(base - a) - (*base <= x ? 0 : 1);
}

// --- lanes: L pixels side by side ---------------------------------------------------------------------------
//
// Each stage below is a loop over L pixels (one sample each) with no calls and no branches, which the compiler
// turns into SIMD code; the sines, arcus functions and exp2 are polynomials for that reason (Cephes's, within
// 2 ulp of the library functions). Table searches and texel look-ups stay scalar per lane.

constexpr int L = 8;

// sin and cos of x in [-2 pi, 2 pi]: reduced to [-pi/4, pi/4] by quadrant (pi/2 split in three for exactness)
inline void sincos_poly(float x, float* s, float* c) {
  float q = std::floor(x * 0.636619772367581343f + 0.5f);
  float y = ((x - q * 1.5703125f) - q * 4.837512969970703125e-4f) - q * 7.54978995489188216e-8f;
  float z = y * y;
  float sy = ((-1.9515295891e-4f * z + 8.3321608736e-3f) * z - 1.6666654611e-1f) * z * y + y;
  float cy = ((2.443315711809948e-5f * z - 1.388731625493765e-3f) * z + 4.166664568298827e-2f) * z * z - 0.5f * z + 1.f;
  int qi = static_cast<int>(q);
  float ss = (qi & 1) ? cy : sy, cc = (qi & 1) ? sy : cy;  // quadrants: (s, c), (c, -s), (-s, -c), (-c, s)
  *s = (qi & 2) ? -ss : ss;
  *c = ((qi + 1) & 2) ? -cc : cc;
}

inline float exp2_poly(float x) {  // 2^x for x in [-126, 127]
  float n = std::floor(x + 0.5f), f = x - n;
  float p = (((((1.535336188319500e-4f * f + 1.339887440266574e-3f) * f + 9.618437357674640e-3f) * f +
               5.550332471162809e-2f) * f + 2.402264791363012e-1f) * f + 6.931472028550421e-1f) * f + 1.f;
  return p * __builtin_bit_cast(float, (static_cast<int32_t>(n) + 127) << 23);
}

inline float atan2_poly(float y, float x) {
  float ax = std::fabs(x), ay = std::fabs(y);
  float a = std::min(ax, ay) / std::max(std::max(ax, ay), 1e-30f);  // in [0, 1]
  bool big = a > 0.414213562373095049f;  // tan(pi/8): atan(a) = pi/4 + atan((a - 1) / (a + 1))
  float t = big ? (a - 1.f) / (a + 1.f) : a;
  float z = t * t;
  float r = (((8.05374449538e-2f * z - 1.38776856032e-1f) * z + 1.99777106478e-1f) * z - 3.33329491539e-1f) * z * t + t;
  r = big ? r + 0.785398163397448310f : r;
  r = ay > ax ? 1.57079632679489662f - r : r;
  r = x < 0 ? kPi - r : r;
  return y < 0 ? -r : r;
}

inline float acos_poly(float z) {  // z in [-1, 1]
  float a = std::fabs(z);
  bool big = a > 0.5f;  // acos(a) = 2 asin(sqrt((1 - a) / 2)), else pi/2 - asin(a)
  float w = big ? 0.5f * (1.f - a) : a * a;
  float x = big ? std::sqrt(w) : a;
  float asin = ((((4.2163199048e-2f * w + 2.4181311049e-2f) * w + 4.5470025998e-2f) * w + 7.4953002686e-2f) * w +
                1.6666752422e-1f) * w * x + x;
  float r = big ? 2.f * asin : 1.57079632679489662f - asin;
  return z < 0 ? kPi - r : r;
}

// The ShadingPoint (Pixel) of L pixels, one array per field. Lanes past the end repeat the last pixel.
struct PixelLanes {
  float nx[L], ny[L], nz[L], vx[L], vy[L], vz[L], ax[L], ay[L], az[L], tx[L], ty[L], tz[L], bx[L], by[L], bz[L];
  float alpha[L], metallic[L], eta[L], spec_on[L], p_spec[L], dop0[L], dop1[L], dop2[L], four_ndv[L], view_geo[L];
  float dielectric[L];
  float rot[9][L];  // world -> light rotation of each lane's image (unused without one)
  int64_t img[L];
  int64_t first;
  int count;
};

void load_lanes(const Scene& s, int64_t first, int64_t n, PixelLanes* P) {
  P->first = first;
  P->count = static_cast<int>(std::min<int64_t>(L, n - first));
  for (int l = 0; l < L; ++l) {
    int64_t i = first + std::min(l, P->count - 1);
    Pixel p = make_pixel(s, i);
    P->nx[l] = p.n.x, P->ny[l] = p.n.y, P->nz[l] = p.n.z, P->vx[l] = p.v.x, P->vy[l] = p.v.y, P->vz[l] = p.v.z;
    P->ax[l] = p.albedo.x, P->ay[l] = p.albedo.y, P->az[l] = p.albedo.z;
    P->tx[l] = p.t.x, P->ty[l] = p.t.y, P->tz[l] = p.t.z, P->bx[l] = p.b.x, P->by[l] = p.b.y, P->bz[l] = p.b.z;
    P->alpha[l] = p.alpha, P->metallic[l] = p.metallic, P->eta[l] = p.eta, P->spec_on[l] = p.spec_on;
    P->p_spec[l] = p.p_spec, P->four_ndv[l] = p.four_n_dot_v, P->view_geo[l] = p.view_geometry;
    P->dop0[l] = p.diffuse_over_pi[0], P->dop1[l] = p.diffuse_over_pi[1], P->dop2[l] = p.diffuse_over_pi[2];
    P->dielectric[l] = p.dielectric ? 1.f : 0.f;
    P->img[l] = s.batch[i];
    for (int e = 0; e < 9; ++e) P->rot[e][l] = s.rot ? s.rot[9 * (s.br == 1 ? 0 : P->img[l]) + e] : 0.f;
  }
}

struct Dirs {
  float x[L], y[L], z[L];
};

// ShadingPoint.sample_directions: GGX half vector by inverse transform, or the cosine lobe (u2 picks)
void brdf_directions(const PixelLanes& P, const float* u0, const float* u1, const float* u2, Dirs* d) {
#pragma omp simd
  for (int l = 0; l < L; ++l) {
    float xi = clampf(u0[l], 0.f, 1 - 1e-7f);
    float ratio = std::sqrt(xi / (1 - xi));
    float ar = P.alpha[l] * ratio;
    float cos_h = 1.f / std::sqrt(1 + ar * ar);
    float sin_h = P.alpha[l] * ratio * cos_h;
    float sp, cp;
    sincos_poly(2 * kPi * u1[l], &sp, &cp);
    // specular: l = 2 (v.h) h - v with h = (sin_h cos, sin_h sin, cos_h) in the tangent frame
    float hl0 = sin_h * cp, hl1 = sin_h * sp;
    float hx = (hl0 * P.tx[l] + hl1 * P.bx[l]) + cos_h * P.nx[l];
    float hy = (hl0 * P.ty[l] + hl1 * P.by[l]) + cos_h * P.ny[l];
    float hz = (hl0 * P.tz[l] + hl1 * P.bz[l]) + cos_h * P.nz[l];
    float vh2 = 2 * (P.vx[l] * hx + P.vy[l] * hy + P.vz[l] * hz);
    // diffuse: cosine-weighted (r cos, r sin, sqrt(1 - u0))
    float r = std::sqrt(u0[l]), cz = std::sqrt(std::max(1 - u0[l], 0.f));
    float dl0 = r * cp, dl1 = r * sp;
    bool spec = u2[l] < P.p_spec[l];
    d->x[l] = spec ? vh2 * hx - P.vx[l] : (dl0 * P.tx[l] + dl1 * P.bx[l]) + cz * P.nx[l];
    d->y[l] = spec ? vh2 * hy - P.vy[l] : (dl0 * P.ty[l] + dl1 * P.by[l]) + cz * P.ny[l];
    d->z[l] = spec ? vh2 * hz - P.vz[l] : (dl0 * P.tz[l] + dl1 * P.bz[l]) + cz * P.nz[l];
  }
}

// EnvMap.sample: a row from the marginal, a column from the row's conditional, uniform in solid angle inside
// the texel (float64, as the tables). The lanes' binary searches run in lockstep, overlapping their latencies.
void envmap_directions(const Scene& s, const PixelLanes& P, const float* u0f, const float* u1f, Dirs* d) {
  double target[L], row_lo[L], row_p[L];
  int64_t row[L], idx[L];
  const double *cdf[L], *row_cdf[L];
  for (int l = 0; l < L; ++l) {
    int64_t t = s.bt == 1 ? 0 : P.img[l];
    cdf[l] = s.cdf + t * (s.h * s.w + 1);
    row_cdf[l] = s.row_cdf + t * (s.h + 1);
    row[l] = std::min(std::max(last_not_above(row_cdf[l], s.h + 1, u0f[l]), int64_t(0)), s.h - 1);
  }
  for (int l = 0; l < L; ++l) {
    row_lo[l] = row_cdf[l][row[l]];
    row_p[l] = row_cdf[l][row[l] + 1] - row_lo[l];
    target[l] = row_lo[l] + static_cast<double>(u1f[l]) * row_p[l];
    // searched inside the row's span only: the same index as a search of the whole cdf clamped to the row
    idx[l] = row[l] * s.w + last_not_above(cdf[l] + row[l] * s.w, s.w + 1, target[l]);
  }
  double lo[L], hi[L], ce0[L], ce1[L], col[L];
  for (int l = 0; l < L; ++l) {  // the texel's cdf step and its row's cos(theta) edges
    int64_t r = row[l], i = std::min(std::max(idx[l], r * s.w), r * s.w + (s.w - 1));
    lo[l] = cdf[l][i], hi[l] = cdf[l][i + 1], ce0[l] = s.cos_edges[r], ce1[l] = s.cos_edges[r + 1];
    col[l] = static_cast<double>(i - r * s.w);
  }
#pragma omp simd
  for (int l = 0; l < L; ++l) {
    double frac_col = std::min(std::max((target[l] - lo[l]) / (hi[l] - lo[l]), 0.0), 1.0);
    double frac_row = std::min(std::max((u0f[l] - row_lo[l]) / row_p[l], 0.0), 1.0);
    double cos_theta = ce0[l] + frac_row * (ce1[l] - ce0[l]);
    double u = (col[l] + frac_col) / s.w;
    // sin and cos of theta = acos(cos_theta), without the round trip; phi's in float (an ulp of a direction)
    double ct = std::min(std::max(cos_theta, -1.0), 1.0);
    float st = static_cast<float>(std::sqrt(std::max(1 - ct * ct, 0.0)));
    float sp, cp;
    sincos_poly(static_cast<float>((0.5 - u) * 2 * kPiD), &sp, &cp);
    float x = st * cp, y = st * sp, z = static_cast<float>(ct);
    if (s.rot) {  // to the world: d @ R (row vector), i.e. R^T d
      float wx = x * P.rot[0][l] + y * P.rot[3][l] + z * P.rot[6][l];
      float wy = x * P.rot[1][l] + y * P.rot[4][l] + z * P.rot[7][l];
      float wz = x * P.rot[2][l] + y * P.rot[5][l] + z * P.rot[8][l];
      x = wx, y = wy, z = wz;
    }
    d->x[l] = x, d->y[l] = y, d->z[l] = z;
  }
}

// ShadingPoint.eval_and_pdf: f(l, v) (n.l) per channel and the BRDF sampling pdf of direction d (0 below n)
void eval_and_pdf(const Scene& s, const PixelLanes& P, const Dirs& d, float* f0, float* f1, float* f2, float* pdf) {
  float g[L];  // geometry_term(n.v, clamp(n.l, 1e-6, 1))
  if (s.smith) {
#pragma omp simd
    for (int l = 0; l < L; ++l) {
      float ndl = clampf(P.nx[l] * d.x[l] + P.ny[l] * d.y[l] + P.nz[l] * d.z[l], 1e-6f, 1.f);
      g[l] = 1.f / (1 + P.view_geo[l] + smith_lambda(ndl, P.alpha[l]));
    }
  } else {
#pragma omp simd
    for (int l = 0; l < L; ++l) {
      float ndl = clampf(P.nx[l] * d.x[l] + P.ny[l] * d.y[l] + P.nz[l] * d.z[l], 1e-6f, 1.f);
      g[l] = P.view_geo[l] * schlick_g1(clampf(ndl, 0.f, 1.f), P.alpha[l]);
    }
  }
#pragma omp simd
  for (int l = 0; l < L; ++l) {
    float n_dot_l = P.nx[l] * d.x[l] + P.ny[l] * d.y[l] + P.nz[l] * d.z[l];
    float hx = d.x[l] + P.vx[l], hy = d.y[l] + P.vy[l], hz = d.z[l] + P.vz[l];
    float hn = std::max(std::sqrt(hx * hx + hy * hy + hz * hz), 1e-12f);  // F.normalize
    hx = hx / hn, hy = hy / hn, hz = hz / hn;
    float n_dot_h = P.nx[l] * hx + P.ny[l] * hy + P.nz[l] * hz;
    float v_dot_h_raw = P.vx[l] * hx + P.vy[l] * hy + P.vz[l] * hz;
    float dd = ggx_d(n_dot_h, P.alpha[l]);
    float ndl = clampf(n_dot_l, 1e-6f, 1.f);
    float vdh = clampf(v_dot_h_raw, 0.f, 1.f);
    float spec = dd * g[l] / P.four_ndv[l];
    float f_d = P.dielectric[l] * (fresnel_dielectric(vdh, P.eta[l]) * P.spec_on[l]);  // weighted by 1 - m
    float e = exp2_poly((-5.55473f * vdh - 6.98316f) * vdh);
    float m = P.metallic[l], dm = (1 - m) * f_d;
    bool above = n_dot_l > 0;
    f0[l] = above ? (dm + m * (P.ax[l] + (1 - P.ax[l]) * e)) * spec + P.dop0[l] * ndl : 0.f;
    f1[l] = above ? (dm + m * (P.ay[l] + (1 - P.ay[l]) * e)) * spec + P.dop1[l] * ndl : 0.f;
    f2[l] = above ? (dm + m * (P.az[l] + (1 - P.az[l]) * e)) * spec + P.dop2[l] * ndl : 0.f;
    float pdf_spec = dd * clampf(n_dot_h, 0.f, 1.f) / (4 * std::max(v_dot_h_raw, 1e-6f));
    float pdf_diff = std::max(n_dot_l, 0.f) / kPi;
    pdf[l] = above ? P.p_spec[l] * pdf_spec + (1 - P.p_spec[l]) * pdf_diff : 0.f;
  }
}

// direction_to_equirect_uv of the normalised direction in the light's frame
void envmap_uv(const Scene& s, const PixelLanes& P, const Dirs& d, float* u, float* v) {
#pragma omp simd
  for (int l = 0; l < L; ++l) {
    float n = std::max(std::sqrt(d.x[l] * d.x[l] + d.y[l] * d.y[l] + d.z[l] * d.z[l]), 1e-12f);
    float x = d.x[l] / n, y = d.y[l] / n, z = d.z[l] / n;
    if (s.rot) {
      float rx = P.rot[0][l] * x + P.rot[1][l] * y + P.rot[2][l] * z;
      float ry = P.rot[3][l] * x + P.rot[4][l] * y + P.rot[5][l] * z;
      float rz = P.rot[6][l] * x + P.rot[7][l] * y + P.rot[8][l] * z;
      x = rx, y = ry, z = rz;
    }
    float uu = 0.5f - atan2_poly(y, x) / (2 * kPi);
    u[l] = uu - std::floor(uu);  // Python's % 1.0 (1.0 itself for a tiny negative u, as torch.remainder)
    v[l] = acos_poly(clampf(z, -1.f, 1.f)) / kPi;
  }
}

// fn(lane, fw, taps) for every valid lane: the sample's term f L w is fw x the look-up at the taps.
// u: the chunk's uniforms (N, spp, dim); sample k of each lane's pixel.
template <typename F>
void shade_sample(const Scene& s, const PixelLanes& P, bool brdf, const float* u, int64_t spp, int64_t dim, int64_t k,
                  F fn) {
  float u0[L], u1[L], u2[L];
  for (int l = 0; l < L; ++l) {
    const float* ul = u + ((P.first + std::min(l, P.count - 1)) * spp + k) * dim;
    u0[l] = ul[0], u1[l] = ul[1], u2[l] = brdf ? ul[2] : 0.f;
  }
  Dirs d;
  if (brdf) brdf_directions(P, u0, u1, u2, &d);
  else envmap_directions(s, P, u0, u1, &d);
  float f0[L], f1[L], f2[L], pdf[L], ue[L], ve[L];
  eval_and_pdf(s, P, d, f0, f1, f2, pdf);
  envmap_uv(s, P, d, ue, ve);
  for (int l = 0; l < P.count; ++l) {
    float denom = s.n_brdf * pdf[l];
    if (s.mis) denom += s.n_light * texel_pdf(s, P.img[l], ue[l], ve[l]);
    float weight = 1.f / std::max(denom, 1e-12f);
    const float fw[3] = {f0[l] * weight, f1[l] * weight, f2[l] * weight};
    fn(l, fw, bilinear_taps(s, P.img[l], ue[l], ve[l]));
  }
}

Scene make_scene(const std::vector<torch::Tensor>& point, const torch::Tensor& batch, const torch::Tensor& image,
                 const torch::Tensor& rot, const std::vector<torch::Tensor>& tables, bool smith, bool mis,
                 int64_t n_brdf, int64_t n_light) {
  Scene s;
  s.normal = point[0].data_ptr<float>();
  s.view = point[1].data_ptr<float>();
  s.albedo = point[2].data_ptr<float>();
  s.alpha = point[3].data_ptr<float>();
  s.metallic = point[4].data_ptr<float>();
  s.specular = point[5].data_ptr<float>();
  s.batch = batch.data_ptr<int64_t>();
  s.image = image.data_ptr<float>();
  s.bi = image.size(0);
  s.h = image.size(1);
  s.w = image.size(2);
  s.rot = rot.numel() ? rot.data_ptr<float>() : nullptr;
  s.br = rot.numel() ? rot.size(0) : 1;
  if (mis) {
    s.cdf = tables[0].data_ptr<double>();
    s.row_cdf = tables[1].data_ptr<double>();
    s.tex_pdf = tables[2].data_ptr<double>();
    s.cos_edges = tables[3].data_ptr<double>();
    s.bt = tables[0].size(0);
  } else {
    s.cdf = s.row_cdf = s.tex_pdf = s.cos_edges = nullptr;
    s.bt = 1;
  }
  s.smith = smith;
  s.mis = mis;
  s.n_brdf = n_brdf;
  s.n_light = n_light;
  return s;
}

void check_inputs(const std::vector<torch::Tensor>& point, const torch::Tensor& batch, const torch::Tensor& image,
                  const torch::Tensor& rot, const std::vector<torch::Tensor>& tables, bool mis,
                  const torch::Tensor& u) {
  TORCH_CHECK(point.size() == 6, "point: normal, view, albedo, alpha, metallic, specular");
  for (const auto& t : point)
    TORCH_CHECK(t.is_contiguous() && t.scalar_type() == torch::kFloat && t.device().is_cpu(),
                "point tensors must be contiguous float32 CPU tensors");
  int64_t n = point[0].size(0);
  TORCH_CHECK(batch.numel() == n && batch.scalar_type() == torch::kLong && batch.is_contiguous(), "batch: (N,) int64");
  TORCH_CHECK(image.dim() == 4 && image.size(3) == 3 && image.is_contiguous() && image.scalar_type() == torch::kFloat,
              "image: contiguous float32 (B, H, W, 3)");
  TORCH_CHECK(rot.numel() == 0 || (rot.dim() == 3 && rot.is_contiguous() && rot.scalar_type() == torch::kFloat),
              "rot: empty or contiguous float32 (B, 3, 3)");
  if (mis) {
    TORCH_CHECK(tables.size() == 4, "tables: cdf, row_cdf, pdf, cos_edges");
    for (const auto& t : tables)
      TORCH_CHECK(t.is_contiguous() && t.scalar_type() == torch::kDouble, "tables must be contiguous float64");
  }
  TORCH_CHECK(u.dim() == 3 && u.size(0) == n && u.is_contiguous() && u.scalar_type() == torch::kFloat,
              "u: contiguous float32 (N, S, 2 or 3)");
}

// fn(begin, end, part) over [0, n) cut into one contiguous range per thread of torch's own intra-op pool (built
// with -fopenmp, the library binds to the libgomp that torch has loaded: one OpenMP runtime, no idle threads
// spinning against ours). The part index, not the thread's, tells a range apart: safe wherever it is called.
int64_t num_parts(int64_t n) {
  return std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), (n + 1023) / 1024));
}

template <typename F>
void parallel_ranges(int64_t n, int64_t parts, F fn) {
  at::parallel_for(0, parts, 1, [&](int64_t p0, int64_t p1) {
    for (int64_t p = p0; p < p1; ++p) fn(p * n / parts, (p + 1) * n / parts, p);
  });
}

}  // namespace

// Sum over the chunk's samples (N, 3) of f L w. kind 0: BRDF samples (u (N, S, 3)); 1: env-map samples (N, S, 2).
torch::Tensor forward(std::vector<torch::Tensor> point, torch::Tensor batch, torch::Tensor image, torch::Tensor rot,
                      std::vector<torch::Tensor> tables, torch::Tensor u, int64_t kind, bool smith, bool mis,
                      int64_t n_brdf, int64_t n_light) {
  check_inputs(point, batch, image, rot, tables, mis, u);
  Scene s = make_scene(point, batch, image, rot, tables, smith, mis, n_brdf, n_light);
  int64_t n = u.size(0), spp = u.size(1), dim = u.size(2);
  auto out = torch::zeros({n, 3}, image.options());
  float* o = out.data_ptr<float>();
  const float* uu = u.data_ptr<float>();
  parallel_ranges(n, num_parts(n), [&](int64_t begin, int64_t end, int64_t) {
    PixelLanes P;
    for (int64_t first = begin; first < end; first += L) {
      load_lanes(s, first, end, &P);
      float acc[L][3] = {};
      for (int64_t k = 0; k < spp; ++k) {
        shade_sample(s, P, kind == 0, uu, spp, dim, k, [&](int l, const float* fw, const Taps& t) {
          for (int c = 0; c < 3; ++c) {
            const float* im = s.image + c;
            float look = (im[3 * t.idx[0]] * t.wx0 + im[3 * t.idx[1]] * t.wx1) * t.wy0 +
                         (im[3 * t.idx[2]] * t.wx0 + im[3 * t.idx[3]] * t.wx1) * t.wy1;
            acc[l][c] += fw[c] * look;
          }
        });
      }
      for (int l = 0; l < P.count; ++l)
        for (int c = 0; c < 3; ++c) o[3 * (first + l) + c] = acc[l][c];
    }
  });
  return out;
}

// d (sum over the chunk's samples of f L w) / d image, contracted with grad_out (N, 3): (Bi, H, W, 3).
torch::Tensor backward_image(std::vector<torch::Tensor> point, torch::Tensor batch, torch::Tensor image,
                             torch::Tensor rot, std::vector<torch::Tensor> tables, torch::Tensor u, int64_t kind,
                             bool smith, bool mis, int64_t n_brdf, int64_t n_light, torch::Tensor grad_out) {
  check_inputs(point, batch, image, rot, tables, mis, u);
  TORCH_CHECK(grad_out.is_contiguous() && grad_out.scalar_type() == torch::kFloat && grad_out.size(0) == u.size(0),
              "grad_out: contiguous float32 (N, 3)");
  Scene s = make_scene(point, batch, image, rot, tables, smith, mis, n_brdf, n_light);
  int64_t n = u.size(0), spp = u.size(1), dim = u.size(2);
  const float* uu = u.data_ptr<float>();
  const float* go = grad_out.data_ptr<float>();
  int64_t parts = num_parts(n);
  // one gradient image per range, summed at the end: no atomics, deterministic for a thread count
  auto partial = torch::zeros({parts, s.bi, s.h, s.w, 3}, image.options());
  float* part = partial.data_ptr<float>();
  int64_t stride = s.bi * s.h * s.w * 3;
  parallel_ranges(n, parts, [&](int64_t begin, int64_t end, int64_t k) {
    float* g = part + k * stride;
    PixelLanes P;
    for (int64_t first = begin; first < end; first += L) {
      load_lanes(s, first, end, &P);
      for (int64_t k = 0; k < spp; ++k) {
        shade_sample(s, P, kind == 0, uu, spp, dim, k, [&](int l, const float* fw, const Taps& t) {
          const float wt[4] = {t.wx0 * t.wy0, t.wx1 * t.wy0, t.wx0 * t.wy1, t.wx1 * t.wy1};
          for (int c = 0; c < 3; ++c) {
            float gc = go[3 * (first + l) + c] * fw[c];
            for (int q = 0; q < 4; ++q) g[3 * t.idx[q] + c] += gc * wt[q];
          }
        });
      }
    }
  });
  return partial.sum(0);
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "MC env-map shading of a chunk of samples (N, 3)");
  m.def("backward_image", &backward_image, "gradient of forward w.r.t. the env map, contracted with grad_out");
}
