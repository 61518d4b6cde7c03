// Fused Monte-Carlo shading of packed pixels under an equirectangular env map (CPU, float32).
//
// One pass per chunk of samples: BRDF or env-map direction sampling, BRDF value and pdf, bilinear radiance,
// MIS weight (balance heuristic), summed over the samples of each pixel. The backward scatters
// grad_out x f x weight into the four texels of each sample's bilinear look-up: the gradient w.r.t. the
// env map alone (the Python caller uses this path only when nothing else needs a gradient).
//
// Every formula mirrors the PyTorch code it replaces, operation for operation, so that values agree to float
// rounding (tests/dibrpp/test_mc_native.py): dibrpp/brdf.py (ShadingPoint.sample_directions, eval, pdf,
// fresnel, diffuse_weight, specular_selection_probability), dibrpp/lights.py (EnvMap._bilinear, sample, pdf)
// and dibrpp/shading.py (_MCPlan.terms). Change one, change both.
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
inline Vec3 operator+(Vec3 a, Vec3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 operator-(Vec3 a, Vec3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 operator*(float s, Vec3 a) { return {s * a.x, s * a.y, s * a.z}; }
inline float dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline float clampf(float x, float lo, float hi) { return std::min(std::max(x, lo), hi); }
inline Vec3 normalized(Vec3 a) {  // F.normalize(eps=1e-12)
  float n = std::max(std::sqrt(dot(a, a)), 1e-12f);
  return {a.x / n, a.y / n, a.z / n};
}

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

float fresnel_dielectric(float cos_i, float eta) {
  float c = clampf(cos_i, 0.f, 1.f);
  float g2 = eta * eta - 1 + c * c;
  float g = std::sqrt(std::max(g2, 0.f));
  float a = (g - c) / std::max(g + c, 1e-12f);
  float b = (c * (g + c) - 1) / (c * (g - c) + 1);
  return g2 > 0 ? 0.5f * a * a * (1 + b * b) : 1.f;
}

float smith_lambda(float cos, float alpha) {
  float c = clampf(cos, 1e-6f, 1.f);
  float c2 = c * c;
  float tan2 = (1 - c2) / c2;
  return 0.5f * (std::sqrt(1 + alpha * alpha * tan2) - 1);
}

float schlick_g1(float c, float alpha) { return c / (c * (1 - alpha) + alpha); }

// G(l, v) given the pixel's view_geometry (Smith lambda(n.v) or Schlick G1(n.v))
float geometry_term(float view_geometry, float n_dot_l, float alpha, bool smith) {
  if (smith) return 1.f / (1 + view_geometry + smith_lambda(n_dot_l, alpha));
  return view_geometry * schlick_g1(clampf(n_dot_l, 0.f, 1.f), alpha);
}

float ggx_d(float n_dot_h, float alpha) {
  float a2 = alpha * alpha;
  float c = clampf(n_dot_h, 0.f, 1.f);
  float c2 = c * c;
  float t = c2 * (a2 - 1) + 1;
  return a2 / (kPi * (t * t));
}

// Per-pixel quantities of a ShadingPoint that do not depend on the light direction.
struct Pixel {
  Vec3 n, v, albedo, t, b;
  float alpha, metallic, n_dot_v, eta, spec_on, p_spec;
  Vec3 diffuse_weight;
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
  p.n_dot_v = clampf(dot(p.n, p.v), 1e-4f, 1.f);
  float f0 = clampf(0.04f * 2 * specular, 0.f, 0.999f);  // dielectric_f0: ((1.5 - 1) / (1.5 + 1))^2 = 0.04
  float sq = std::sqrt(clampf(f0, 1e-8f, 0.999f));
  p.eta = (1 + sq) / (1 - sq);
  p.spec_on = specular > 0 ? 1.f : 0.f;
  float f_d = fresnel_dielectric(p.n_dot_v, p.eta) * p.spec_on;
  float dw = (1 - p.metallic) * (1 - f_d);
  p.diffuse_weight = dw * p.albedo;
  p.diffuse_over_pi[0] = p.diffuse_weight.x / kPi;
  p.diffuse_over_pi[1] = p.diffuse_weight.y / kPi;
  p.diffuse_over_pi[2] = p.diffuse_weight.z / kPi;
  p.four_n_dot_v = 4 * p.n_dot_v;
  p.dielectric = (1 - p.metallic) != 0 && p.spec_on != 0;
  float spec_w = (1 - p.metallic) * f0 * p.spec_on + p.metallic;
  float diff_w = (p.diffuse_weight.x + p.diffuse_weight.y + p.diffuse_weight.z) / 3;
  float prob = spec_w / std::max(spec_w + diff_w, 1e-8f);
  p.p_spec = (spec_w > 0 && diff_w > 0) ? clampf(prob, 0.25f, 0.9f) : prob;
  // tangent frame (Duff et al. 2017), as brdf._tangent_frame
  float sign = p.n.z >= 0 ? 1.f : -1.f;
  float a = -1.f / (sign + p.n.z);
  float bb = p.n.x * p.n.y * a;
  p.t = {1 + sign * (p.n.x * p.n.x) * a, sign * bb, -sign * p.n.x};
  p.b = {bb, sign + (p.n.y * p.n.y) * a, -p.n.y};
  p.view_geometry = s.smith ? smith_lambda(p.n_dot_v, p.alpha) : schlick_g1(clampf(p.n_dot_v, 0.f, 1.f), p.alpha);
  return p;
}

Vec3 to_world(const Pixel& p, Vec3 l) { return (l.x * p.t + l.y * p.b) + l.z * p.n; }

Vec3 sample_brdf_direction(const Pixel& p, const float* u) {
  float xi = clampf(u[0], 0.f, 1 - 1e-7f);
  float ratio = std::sqrt(xi / (1 - xi));
  float ar = p.alpha * ratio;
  float cos_h = 1.f / std::sqrt(1 + ar * ar);
  float sin_h = p.alpha * ratio * cos_h;
  float phi = 2 * kPi * u[1];
  float cp = std::cos(phi), sp = std::sin(phi);
  if (u[2] < p.p_spec) {
    Vec3 h = to_world(p, {sin_h * cp, sin_h * sp, cos_h});
    return (2 * dot(p.v, h)) * h - p.v;
  }
  float r = std::sqrt(u[0]);
  return to_world(p, {r * cp, r * sp, std::sqrt(std::max(1 - u[0], 0.f))});
}

// f(l, v) (n.l) (3 channels) and the BRDF sampling pdf of direction l.
void eval_and_pdf(const Scene& s, const Pixel& p, Vec3 l, float f[3], float* pdf) {
  float n_dot_l = dot(p.n, l);
  Vec3 h = normalized(l + p.v);
  float n_dot_h = dot(p.n, h);
  float v_dot_h_raw = dot(p.v, h);
  float d = ggx_d(n_dot_h, p.alpha);
  if (!(n_dot_l > 0)) {
    f[0] = f[1] = f[2] = 0.f;
    *pdf = 0.f;
    return;
  }
  float ndl = clampf(n_dot_l, 1e-6f, 1.f);
  float vdh = clampf(v_dot_h_raw, 0.f, 1.f);
  float spec = d * geometry_term(p.view_geometry, ndl, p.alpha, s.smith) / p.four_n_dot_v;
  float f_d = p.dielectric ? fresnel_dielectric(vdh, p.eta) * p.spec_on : 0.f;  // else weighted by 0 below
  float e = std::exp2((-5.55473f * vdh - 6.98316f) * vdh);
  const float a3[3] = {p.albedo.x, p.albedo.y, p.albedo.z};
  for (int c = 0; c < 3; ++c) {
    float f_m = a3[c] + (1 - a3[c]) * e;
    float fres = (1 - p.metallic) * f_d + p.metallic * f_m;
    f[c] = fres * spec + p.diffuse_over_pi[c] * ndl;
  }
  float pdf_spec = d * clampf(n_dot_h, 0.f, 1.f) / (4 * std::max(v_dot_h_raw, 1e-6f));
  float pdf_diff = std::max(n_dot_l, 0.f) / kPi;
  *pdf = p.p_spec * pdf_spec + (1 - p.p_spec) * pdf_diff;
}

// --- env map (dibrpp/lights.py) ---------------------------------------------------------------------------

Vec3 world_to_light(const Scene& s, int64_t img, Vec3 d) {
  if (!s.rot) return d;
  const float* r = s.rot + 9 * (s.br == 1 ? 0 : img);
  return {r[0] * d.x + r[1] * d.y + r[2] * d.z, r[3] * d.x + r[4] * d.y + r[5] * d.z,
          r[6] * d.x + r[7] * d.y + r[8] * d.z};
}

Vec3 light_to_world(const Scene& s, int64_t img, Vec3 d) {  // d @ R (row vector): R^T d
  if (!s.rot) return d;
  const float* r = s.rot + 9 * (s.br == 1 ? 0 : img);
  return {d.x * r[0] + d.y * r[3] + d.z * r[6], d.x * r[1] + d.y * r[4] + d.z * r[7],
          d.x * r[2] + d.y * r[5] + d.z * r[8]};
}

// direction_to_equirect_uv of a light-frame unit direction
inline void equirect_uv(Vec3 d, float* u, float* v) {
  float uu = 0.5f - std::atan2(d.y, d.x) / (2 * kPi);
  uu = uu - std::floor(uu);  // Python's % 1.0 (1.0 itself for a tiny negative u, as torch.remainder)
  *u = uu;
  *v = std::acos(clampf(d.z, -1.f, 1.f)) / kPi;
}

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

constexpr int kLockstep = 8;

// Directions (world) of count <= kLockstep env-map samples, uniforms uf (count, 2). Their binary searches run in
// lockstep: the load latencies of independent searches overlap instead of adding up.
void sample_envmap_directions(const Scene& s, int64_t img, const float* uf, int count, Vec3* out) {
  int64_t t = s.bt == 1 ? 0 : img;
  const double* cdf = s.cdf + t * (s.h * s.w + 1);
  const double* row_cdf = s.row_cdf + t * (s.h + 1);
  double u0[kLockstep], u1[kLockstep], target[kLockstep], row_lo[kLockstep], row_p[kLockstep];
  int64_t row[kLockstep], idx[kLockstep];
  for (int k = 0; k < count; ++k) {
    u0[k] = uf[2 * k];
    u1[k] = uf[2 * k + 1];
    row[k] = std::min(std::max(last_not_above(row_cdf, s.h + 1, u0[k]), int64_t(0)), s.h - 1);
  }
  for (int k = 0; k < count; ++k) {
    row_lo[k] = row_cdf[row[k]];
    row_p[k] = row_cdf[row[k] + 1] - row_lo[k];
    target[k] = row_lo[k] + u1[k] * row_p[k];
    // searched inside the row's span only: the same index as a search of the whole cdf clamped to the row
    idx[k] = row[k] * s.w + last_not_above(cdf + row[k] * s.w, s.w + 1, target[k]);
  }
  for (int k = 0; k < count; ++k) {
    int64_t r = row[k], i = std::min(std::max(idx[k], r * s.w), r * s.w + (s.w - 1));
    double lo = cdf[i];
    double frac_col = std::min(std::max((target[k] - lo) / (cdf[i + 1] - lo), 0.0), 1.0);
    double frac_row = std::min(std::max((u0[k] - row_lo[k]) / row_p[k], 0.0), 1.0);
    double cos_theta = s.cos_edges[r] + frac_row * (s.cos_edges[r + 1] - s.cos_edges[r]);
    double u = (static_cast<double>(i - r * s.w) + frac_col) / s.w;
    double phi = (0.5 - u) * 2 * kPiD;
    // sin and cos of theta = acos(cos_theta), without the round trip (equal in double to an ulp)
    double ct = std::min(std::max(cos_theta, -1.0), 1.0);
    double st = std::sqrt(std::max(1 - ct * ct, 0.0));
    Vec3 d = {static_cast<float>(st * std::cos(phi)), static_cast<float>(st * std::sin(phi)), static_cast<float>(ct)};
    out[k] = light_to_world(s, img, d);
  }
}

// fn(fw, taps) for each of the spp samples of pixel i (uniforms u: (spp, dim) of this pixel).
template <typename F>
void for_each_sample(const Scene& s, int64_t i, bool brdf, const float* u, int64_t spp, int64_t dim, F fn) {
  Pixel p = make_pixel(s, i);
  int64_t img = s.batch[i];
  Vec3 dirs[kLockstep];
  for (int64_t k0 = 0; k0 < spp; k0 += kLockstep) {
    int count = static_cast<int>(std::min<int64_t>(kLockstep, spp - k0));
    if (brdf) {
      for (int k = 0; k < count; ++k) dirs[k] = sample_brdf_direction(p, u + (k0 + k) * dim);
    } else {
      sample_envmap_directions(s, img, u + k0 * dim, count, dirs);
    }
    // stage by stage over the block (independent dependency chains side by side): f and the BRDF pdf, the
    // map's (u, v) of each direction, then the MIS weight and the bilinear taps
    float f[kLockstep][3], pdf[kLockstep], u_env[kLockstep], v_env[kLockstep];
    for (int k = 0; k < count; ++k) eval_and_pdf(s, p, dirs[k], f[k], &pdf[k]);
    for (int k = 0; k < count; ++k) equirect_uv(world_to_light(s, img, normalized(dirs[k])), &u_env[k], &v_env[k]);
    for (int k = 0; k < count; ++k) {
      float denom = s.n_brdf * pdf[k];
      if (s.mis) denom += s.n_light * texel_pdf(s, img, u_env[k], v_env[k]);
      float weight = 1.f / std::max(denom, 1e-12f);
      const float fw[3] = {f[k][0] * weight, f[k][1] * weight, f[k][2] * weight};
      fn(fw, bilinear_taps(s, img, u_env[k], v_env[k]));  // the sample's term f L w: fw x the look-up at the taps
    }
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

// fn(begin, end, thread) over [0, n) in one contiguous range per thread of torch's own intra-op pool (built with
// -fopenmp, the library binds to the libgomp that torch has loaded: one OpenMP runtime, no idle threads spinning
// against ours).
template <typename F>
void parallel_ranges(int64_t n, F fn) {
  int64_t threads = std::max<int64_t>(1, at::get_num_threads());
  int64_t grain = std::max<int64_t>(1024, (n + threads - 1) / threads);
  at::parallel_for(0, n, grain, [&](int64_t begin, int64_t end) { fn(begin, end, at::get_thread_num()); });
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
  parallel_ranges(n, [&](int64_t begin, int64_t end, int64_t) {
    for (int64_t i = begin; i < end; ++i) {
      float acc[3] = {0.f, 0.f, 0.f};
      for_each_sample(s, i, kind == 0, uu + i * spp * dim, spp, dim, [&](const float* fw, const Taps& t) {
        for (int c = 0; c < 3; ++c) {
          const float* im = s.image + c;
          float l = (im[3 * t.idx[0]] * t.wx0 + im[3 * t.idx[1]] * t.wx1) * t.wy0 +
                    (im[3 * t.idx[2]] * t.wx0 + im[3 * t.idx[3]] * t.wx1) * t.wy1;
          acc[c] += fw[c] * l;
        }
      });
      for (int c = 0; c < 3; ++c) o[3 * i + c] = acc[c];
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
  int64_t threads = std::max<int64_t>(1, at::get_num_threads());
  // one gradient image per thread, summed at the end: no atomics, deterministic for a thread count
  auto partial = torch::zeros({threads, s.bi, s.h, s.w, 3}, image.options());
  float* part = partial.data_ptr<float>();
  int64_t stride = s.bi * s.h * s.w * 3;
  parallel_ranges(n, [&](int64_t begin, int64_t end, int64_t k_thread) {
    float* g = part + k_thread * stride;
    for (int64_t i = begin; i < end; ++i) {
      for_each_sample(s, i, kind == 0, uu + i * spp * dim, spp, dim, [&](const float* fw, const Taps& t) {
        const float wt[4] = {t.wx0 * t.wy0, t.wx1 * t.wy0, t.wx0 * t.wy1, t.wx1 * t.wy1};
        for (int c = 0; c < 3; ++c) {
          float gc = go[3 * i + c] * fw[c];
          for (int q = 0; q < 4; ++q) g[3 * t.idx[q] + c] += gc * wt[q];
        }
      });
    }
  });
  return partial.sum(0);
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "MC env-map shading of a chunk of samples (N, 3)");
  m.def("backward_image", &backward_image, "gradient of forward w.r.t. the env map, contracted with grad_out");
}
