// CPU kernels of the Gaussian-splat renderer: EWA projection and its backward,
// tile binning, front-to-back compositing and its analytic backward.
//
// Plain C ABI on caller-allocated, C-contiguous buffers (no torch headers), so
// that it builds in about a second with g++ and is called through ctypes, which
// releases the GIL for the duration of every call. Each entry point exists for
// float (suffix _f32) and double (_f64). The per-pixel rule is the one of
// soma_ros/core/render_raster.py (the pure-torch reference); see that module
// and soma_ros/core/render.py for the conventions. Single-threaded by design:
// one compute thread per process.
//
// Shapes (V visible splats, C cameras, H x W pixels, K feature channels,
// n_tiles = C * tiles_y * tiles_x, M tile/splat intersections):
//   project:   means [N,3], covs [N,3,3], opac [N], w2c [C,4,4], Kmat [C,3,3]
//              -> cam [C*N] int64, sidx [C*N] int64, mean2d [C*N,2],
//                 conic [C*N,3], cov2d [C*N,3], depth, opac, smin, pmax [C*N];
//              returns V (rows 0..V-1 are filled, ordered by camera then splat)
//   project_bwd: grads of mean2d [V,2], conic [V,3], depth [V], opac [V] ->
//              grads of means [N,3], covs [N,3,3], opac [N] (accumulated; zeroed
//              by the caller)
//   bin_count: mean2d [V,2], conic [V,3], cov2d [V,3], pmax [V], depth [V],
//              cam [V] int64 -> order [V] int32, box [V,4] int32,
//              counts [n_tiles] int32 (zeroed by the caller); returns M
//   bin_fill:  ... -> offsets [n_tiles+1] int32, isect [M] int32 (visible-splat
//              index per tile, front to back)
//   composite_fwd: -> img [C,H,W,K], t_final [C*H*W], n_last [C*H*W] int32
//   composite_bwd: grad_img [C,H,W,K] -> grad [V, 6+K] (accumulated; zeroed
//              by the caller) = d(mx, my, a, b, c, opacity, feat[K])

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <vector>

namespace {

template <typename T>
inline T quad(T a, T b, T c, T x, T y) {
    return T(0.5) * (a * x * x + T(2) * b * x * y + c * y * y);
}

// Minimum of 0.5 (a x^2 + 2 b x y + c y^2) over [x0, x1] x [y0, y1] (a, c > 0).
template <typename T>
T min_quad_on_rect(T x0, T x1, T y0, T y1, T a, T b, T c) {
    if (x0 <= 0 && x1 >= 0 && y0 <= 0 && y1 >= 0) return T(0);
    T best = INFINITY;
    for (T xe : {x0, x1}) {
        T y = std::min(std::max(-b * xe / c, y0), y1);
        best = std::min(best, quad(a, b, c, xe, y));
    }
    for (T ye : {y0, y1}) {
        T x = std::min(std::max(-b * ye / a, x0), x1);
        best = std::min(best, quad(a, b, c, x, ye));
    }
    return best;
}

template <typename T>
int64_t project(int64_t N, int64_t C, const T* means, const T* covs, const T* opac, const T* w2c,
                const T* Kmat, int64_t W, int64_t H, T near_plane, T far_plane, T eps2d,
                T sigma_cutoff, T alpha_min, int clamp_jac, int64_t* cam_out, int64_t* sidx_out,
                T* mean2d, T* conic, T* cov2d, T* depth, T* opac_out, T* smin_out, T* pmax_out) {
    const T log_amin = std::log(alpha_min);
    const T half_cut2 = T(0.5) * sigma_cutoff * sigma_cutoff;
    int64_t V = 0;
    for (int64_t ci = 0; ci < C; ++ci) {
        const T* M = w2c + 16 * ci;
        const T R[9] = {M[0], M[1], M[2], M[4], M[5], M[6], M[8], M[9], M[10]};
        const T t[3] = {M[3], M[7], M[11]};
        const T* Kc = Kmat + 9 * ci;
        const T fx = Kc[0], fy = Kc[4], cx = Kc[2], cy = Kc[5];
        const T tan_fovx = T(0.5) * T(W) / fx, tan_fovy = T(0.5) * T(H) / fy;
        const T lim_xp = (T(W) - cx) / fx + T(0.3) * tan_fovx;
        const T lim_xn = cx / fx + T(0.3) * tan_fovx;
        const T lim_yp = (T(H) - cy) / fy + T(0.3) * tan_fovy;
        const T lim_yn = cy / fy + T(0.3) * tan_fovy;
        for (int64_t n = 0; n < N; ++n) {
            const T* m = means + 3 * n;
            const T z = R[6] * m[0] + R[7] * m[1] + R[8] * m[2] + t[2];
            if (!(z > near_plane && z < far_plane)) continue;
            const T op = opac[n];
            if (!(op >= alpha_min)) continue;
            const T x = R[0] * m[0] + R[1] * m[1] + R[2] * m[2] + t[0];
            const T y = R[3] * m[0] + R[4] * m[1] + R[5] * m[2] + t[1];
            const T inv_z = T(1) / z;
            const T u = fx * x * inv_z + cx;
            const T v = fy * y * inv_z + cy;
            T xz = x * inv_z, yz = y * inv_z;
            if (clamp_jac) {
                xz = std::min(std::max(xz, -lim_xn), lim_xp);
                yz = std::min(std::max(yz, -lim_yn), lim_yp);
            }
            const T j00 = fx * inv_z, j02 = -fx * xz * inv_z;
            const T j11 = fy * inv_z, j12 = -fy * yz * inv_z;
            // camera-frame covariance Sc = (R Sigma) R^T
            const T* S = covs + 9 * n;
            T RS[9];
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j)
                    RS[3 * i + j] = R[3 * i] * S[j] + R[3 * i + 1] * S[3 + j] + R[3 * i + 2] * S[6 + j];
            T Sc[9];
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j)
                    Sc[3 * i + j] = RS[3 * i] * R[3 * j] + RS[3 * i + 1] * R[3 * j + 1] + RS[3 * i + 2] * R[3 * j + 2];
            const T s00 = Sc[0], s01 = Sc[1], s02 = Sc[2], s11 = Sc[4], s12 = Sc[5], s22 = Sc[8];
            const T sxx = j00 * j00 * s00 + T(2) * j00 * j02 * s02 + j02 * j02 * s22 + eps2d;
            const T sxy = j00 * j11 * s01 + j00 * j12 * s02 + j02 * j11 * s12 + j02 * j12 * s22;
            const T syy = j11 * j11 * s11 + T(2) * j11 * j12 * s12 + j12 * j12 * s22 + eps2d;
            const T det = sxx * syy - sxy * sxy;
            const T logo = std::log(op);
            const T smin = std::max(logo - half_cut2, log_amin);
            const T pmax = logo - smin;
            if (!(det > 0) || !std::isfinite(u) || !std::isfinite(v)) continue;
            const T hx = std::sqrt(T(2) * pmax * std::max(sxx, T(0))) + T(1);
            const T hy = std::sqrt(T(2) * pmax * std::max(syy, T(0))) + T(1);
            if (!(u + hx > 0 && u - hx < T(W) && v + hy > 0 && v - hy < T(H))) continue;
            cam_out[V] = ci;
            sidx_out[V] = n;
            mean2d[2 * V] = u;
            mean2d[2 * V + 1] = v;
            conic[3 * V] = syy / det;
            conic[3 * V + 1] = -sxy / det;
            conic[3 * V + 2] = sxx / det;
            cov2d[3 * V] = sxx;
            cov2d[3 * V + 1] = sxy;
            cov2d[3 * V + 2] = syy;
            depth[V] = z;
            opac_out[V] = op;
            smin_out[V] = smin;
            pmax_out[V] = pmax;
            ++V;
        }
    }
    return V;
}

// Backward of project: upstream gradients of the V visible rows (mean2d [V,2],
// conic [V,3], depth [V], opacity [V]) -> accumulated (caller-zeroed) gradients
// of means [N,3], covs [N,3,3] and opacities [N]. Recomputes the forward terms
// from (cam, sidx); cov2d, smin and pmax carry no gradient (as in the torch
// reference, where they only select). The covariance gradient is the one of the
// reference's entry selection (s00, s01, s02, s11, s12, s22 of R Sigma R^T),
// pulled back as R^T G R.
template <typename T>
void project_bwd(int64_t V, const int64_t* cam, const int64_t* sidx, const T* means, const T* covs,
                 const T* w2c, const T* Kmat, int64_t W, int64_t H, int clamp_jac, const T* conic,
                 const T* g_mean2d, const T* g_conic, const T* g_depth, const T* g_opac, T* g_means,
                 T* g_covs, T* g_opacs) {
    for (int64_t r = 0; r < V; ++r) {
        const int64_t ci = cam[r], n = sidx[r];
        const T* M = w2c + 16 * ci;
        const T R[9] = {M[0], M[1], M[2], M[4], M[5], M[6], M[8], M[9], M[10]};
        const T* Kc = Kmat + 9 * ci;
        const T fx = Kc[0], fy = Kc[4], cx = Kc[2], cy = Kc[5];
        const T* m = means + 3 * n;
        const T x = R[0] * m[0] + R[1] * m[1] + R[2] * m[2] + M[3];
        const T y = R[3] * m[0] + R[4] * m[1] + R[5] * m[2] + M[7];
        const T z = R[6] * m[0] + R[7] * m[1] + R[8] * m[2] + M[11];
        const T inv_z = T(1) / z;
        const T xr = x * inv_z, yr = y * inv_z;
        T xz = xr, yz = yr;
        bool xin = true, yin = true;
        if (clamp_jac) {
            const T tan_fovx = T(0.5) * T(W) / fx, tan_fovy = T(0.5) * T(H) / fy;
            const T lim_xp = (T(W) - cx) / fx + T(0.3) * tan_fovx, lim_xn = cx / fx + T(0.3) * tan_fovx;
            const T lim_yp = (T(H) - cy) / fy + T(0.3) * tan_fovy, lim_yn = cy / fy + T(0.3) * tan_fovy;
            xz = std::min(std::max(xr, -lim_xn), lim_xp);
            yz = std::min(std::max(yr, -lim_yn), lim_yp);
            xin = xr > -lim_xn && xr < lim_xp;
            yin = yr > -lim_yn && yr < lim_yp;
        }
        const T j00 = fx * inv_z, j02 = -fx * xz * inv_z;
        const T j11 = fy * inv_z, j12 = -fy * yz * inv_z;
        const T* S = covs + 9 * n;
        T RS[9], Sc[9];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                RS[3 * i + j] = R[3 * i] * S[j] + R[3 * i + 1] * S[3 + j] + R[3 * i + 2] * S[6 + j];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                Sc[3 * i + j] = RS[3 * i] * R[3 * j] + RS[3 * i + 1] * R[3 * j + 1] + RS[3 * i + 2] * R[3 * j + 2];
        const T s00 = Sc[0], s01 = Sc[1], s02 = Sc[2], s11 = Sc[4], s12 = Sc[5], s22 = Sc[8];
        // conic Q = inv(Sigma2d): dL/dSigma2d = -Q G Q, G = [[ga, gb/2], [gb/2, gc]]
        const T qa = conic[3 * r], qb = conic[3 * r + 1], qc = conic[3 * r + 2];
        const T ga = g_conic[3 * r], gb = T(0.5) * g_conic[3 * r + 1], gc = g_conic[3 * r + 2];
        const T p00 = qa * ga + qb * gb, p01 = qa * gb + qb * gc;
        const T p10 = qb * ga + qc * gb, p11 = qb * gb + qc * gc;
        const T gxx = -(p00 * qa + p01 * qb);
        const T gxy = T(-2) * (p00 * qb + p01 * qc);
        const T gyy = -(p10 * qb + p11 * qc);
        // Sigma2d = J Sc J^T on the reference's entries
        T G[9] = {gxx * j00 * j00, gxy * j00 * j11, T(2) * gxx * j00 * j02 + gxy * j00 * j12,
                  T(0), gyy * j11 * j11, gxy * j02 * j11 + T(2) * gyy * j11 * j12,
                  T(0), T(0), gxx * j02 * j02 + gxy * j02 * j12 + gyy * j12 * j12};
        const T g_j00 = gxx * (T(2) * j00 * s00 + T(2) * j02 * s02) + gxy * (j11 * s01 + j12 * s02);
        const T g_j02 = gxx * (T(2) * j00 * s02 + T(2) * j02 * s22) + gxy * (j11 * s12 + j12 * s22);
        const T g_j11 = gyy * (T(2) * j11 * s11 + T(2) * j12 * s12) + gxy * (j00 * s01 + j02 * s12);
        const T g_j12 = gyy * (T(2) * j11 * s12 + T(2) * j12 * s22) + gxy * (j00 * s02 + j02 * s22);
        // world covariance: dL/dSigma = R^T G R
        T GR[9];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                GR[3 * i + j] = G[3 * i] * R[j] + G[3 * i + 1] * R[3 + j] + G[3 * i + 2] * R[6 + j];
        T* gS = g_covs + 9 * n;
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                gS[3 * i + j] += R[i] * GR[j] + R[3 + i] * GR[3 + j] + R[6 + i] * GR[6 + j];
        // mean: u = fx x / z + cx, v = fy y / z + cy, J(x/z, y/z, 1/z), depth = z
        const T gu = g_mean2d[2 * r], gv = g_mean2d[2 * r + 1];
        const T g_xz = xin ? -g_j02 * fx * inv_z : T(0);
        const T g_yz = yin ? -g_j12 * fy * inv_z : T(0);
        const T g_iz = gu * fx * x + gv * fy * y + g_j00 * fx - g_j02 * fx * xz + g_j11 * fy -
                       g_j12 * fy * yz + g_xz * x + g_yz * y;
        const T gx = gu * fx * inv_z + g_xz * inv_z;
        const T gy = gv * fy * inv_z + g_yz * inv_z;
        const T gz = g_depth[r] - g_iz * inv_z * inv_z;
        T* gm = g_means + 3 * n;
        gm[0] += R[0] * gx + R[3] * gy + R[6] * gz;
        gm[1] += R[1] * gx + R[4] * gy + R[7] * gz;
        gm[2] += R[2] * gx + R[5] * gy + R[8] * gz;
        g_opacs[n] += g_opac[r];
    }
}

struct Grid {
    int64_t C, W, H, tile, tx, ty;
    Grid(int64_t C_, int64_t W_, int64_t H_, int64_t tile_)
        : C(C_), W(W_), H(H_), tile(tile_), tx((W_ + tile_ - 1) / tile_), ty((H_ + tile_ - 1) / tile_) {}
    int64_t n_tiles() const { return C * tx * ty; }
};

// Does the cut-off ellipse of splat v reach any pixel centre of tile (tx, ty)?
template <typename T>
inline bool tile_hit(const Grid& g, int64_t tx, int64_t ty, const T* m, const T* cn, T pmax) {
    const T x0 = T(tx * g.tile) + T(0.5), x1 = T(std::min((tx + 1) * g.tile, g.W)) - T(0.5);
    const T y0 = T(ty * g.tile) + T(0.5), y1 = T(std::min((ty + 1) * g.tile, g.H)) - T(0.5);
    const T q = min_quad_on_rect(x0 - m[0], x1 - m[0], y0 - m[1], y1 - m[1], cn[0], cn[1], cn[2]);
    return !(q > pmax * T(1 + 1e-5) + T(1e-5));
}

template <typename T>
int64_t bin_count(int64_t V, const T* mean2d, const T* conic, const T* cov2d, const T* pmax,
                  const T* depth, const int64_t* cam, int64_t C, int64_t W, int64_t H, int64_t tile,
                  int32_t* order, int32_t* box, int32_t* counts) {
    const Grid g(C, W, H, tile);
    std::iota(order, order + V, 0);
    std::stable_sort(order, order + V, [depth](int32_t i, int32_t j) { return depth[i] < depth[j]; });
    int64_t M = 0;
    for (int64_t v = 0; v < V; ++v) {
        int32_t* bx = box + 4 * v;
        bx[0] = 1;
        bx[1] = 0;  // empty unless filled below
        bx[2] = 1;
        bx[3] = 0;
        const T* m = mean2d + 2 * v;
        const T hx = std::sqrt(T(2) * pmax[v] * cov2d[3 * v]) * T(1 + 1e-5) + T(1e-4);
        const T hy = std::sqrt(T(2) * pmax[v] * cov2d[3 * v + 2]) * T(1 + 1e-5) + T(1e-4);
        const T cmin = std::ceil(m[0] - hx - T(0.5)), cmax = std::floor(m[0] + hx - T(0.5));
        const T rmin = std::ceil(m[1] - hy - T(0.5)), rmax = std::floor(m[1] + hy - T(0.5));
        if (!(cmax >= 0 && rmax >= 0 && cmin <= T(W - 1) && rmin <= T(H - 1) && cmin <= cmax && rmin <= rmax))
            continue;
        const int64_t c0 = int64_t(std::max(cmin, T(0))), c1 = int64_t(std::min(cmax, T(W - 1)));
        const int64_t r0 = int64_t(std::max(rmin, T(0))), r1 = int64_t(std::min(rmax, T(H - 1)));
        bx[0] = int32_t(c0 / tile);
        bx[1] = int32_t(c1 / tile);
        bx[2] = int32_t(r0 / tile);
        bx[3] = int32_t(r1 / tile);
        const bool cull = bx[1] > bx[0] && bx[3] > bx[2];
        const int64_t base = cam[v] * g.tx * g.ty;
        for (int64_t ty = bx[2]; ty <= bx[3]; ++ty)
            for (int64_t tx = bx[0]; tx <= bx[1]; ++tx) {
                if (cull && !tile_hit(g, tx, ty, m, conic + 3 * v, pmax[v])) continue;
                ++counts[base + ty * g.tx + tx];
                ++M;
            }
    }
    return M;
}

template <typename T>
void bin_fill(int64_t V, const T* mean2d, const T* conic, const T* pmax, const int64_t* cam,
              int64_t C, int64_t W, int64_t H, int64_t tile, const int32_t* order, const int32_t* box,
              const int32_t* counts, int32_t* offsets, int32_t* isect) {
    const Grid g(C, W, H, tile);
    const int64_t nt = g.n_tiles();
    offsets[0] = 0;
    for (int64_t i = 0; i < nt; ++i) offsets[i + 1] = offsets[i] + counts[i];
    std::vector<int32_t> cursor(offsets, offsets + nt);
    for (int64_t k = 0; k < V; ++k) {  // depth order: every tile list runs front to back
        const int32_t v = order[k];
        const int32_t* bx = box + 4 * v;
        if (bx[0] > bx[1]) continue;
        const T* m = mean2d + 2 * v;
        const bool cull = bx[1] > bx[0] && bx[3] > bx[2];
        const int64_t base = cam[v] * g.tx * g.ty;
        for (int64_t ty = bx[2]; ty <= bx[3]; ++ty)
            for (int64_t tx = bx[0]; tx <= bx[1]; ++tx) {
                if (cull && !tile_hit(g, tx, ty, m, conic + 3 * v, pmax[v])) continue;
                isect[cursor[base + ty * g.tx + tx]++] = v;
            }
    }
}

// exp for the compositing loops. float: a branch-free polynomial that the
// compiler vectorises (relative error < 2e-7 on the argument range used here,
// (-90, 5]); double: std::exp (the float64 path is the exact reference twin).
inline float vexp(float x) {
    x = std::min(std::max(x, -87.0f), 88.0f);
    const float kf = std::nearbyint(x * 1.44269504088896341f);
    float r = x - kf * 0.693145751953125f;
    r = r - kf * 1.42860682030941723212e-6f;
    float p = 1.0f / 5040.0f;
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    const int32_t ki = int32_t(kf);
    int32_t bits;
    std::memcpy(&bits, &p, 4);
    bits += ki * (1 << 23);
    std::memcpy(&p, &bits, 4);
    return p;
}
inline double vexp(double x) { return std::exp(x); }

// Per-splat constants of the pixel rule: alpha = min(exp(rel0 - power) * esmin, alpha_max)
// where rel0 - power > 0, else 0 (rel0 = log(opacity) - s_min, esmin = exp(s_min)).
// hy: half height of the cut-off ellipse {power <= rel0}, sqrt(2 rel0 (Q^-1)_yy)
// with Q the conic, widened by a margin so that rows beyond it are provably outside.
template <typename T>
struct SplatRule {
    T mx, my, a, b, c, rel0, esmin, opac, hy;
    SplatRule(int32_t v, const T* mean2d, const T* conic, const T* opacity, const T* smin)
        : mx(mean2d[2 * v]), my(mean2d[2 * v + 1]), a(conic[3 * v]), b(conic[3 * v + 1]),
          c(conic[3 * v + 2]), rel0(std::log(opacity[v]) - smin[v]), esmin(std::exp(smin[v])),
          opac(opacity[v]) {
        const T det = a * c - b * b;
        hy = det > 0 ? std::sqrt(std::max(T(2) * rel0 * a / det, T(0))) * T(1.0001) + T(1e-3) : T(INFINITY);
    }
    // pixel range [begin, end) of the tile rows (row-major, `tile` wide) that the
    // ellipse can reach; y0 is the pixel-centre y of the tile's first row
    inline void rows(T y0, int64_t tile, int64_t& begin, int64_t& end) const {
        const T lo = std::ceil(my - hy - y0), hi = std::floor(my + hy - y0);
        const int64_t r0 = lo > T(0) ? int64_t(std::min(lo, T(tile))) : 0;
        const int64_t r1 = hi < T(tile - 1) ? (hi < T(-1) ? -1 : int64_t(hi)) : tile - 1;
        begin = r0 * tile;
        end = std::max(r1 + 1, r0) * tile;
    }
};

// Pixel-centre coordinates of one tile, P = tile * tile entries (row-major);
// pixels outside the image are flagged invalid.
template <typename T>
struct TilePixels {
    std::vector<T> px, py;
    std::vector<int64_t> index;  // flat pixel index in [C, H, W], -1 when outside
    T y0 = 0;                     // pixel-centre y of the first row
    void set(const Grid& g, int64_t tid) {
        const int64_t P = g.tile * g.tile;
        px.resize(P);
        py.resize(P);
        index.resize(P);
        const int64_t ci = tid / (g.tx * g.ty), loc = tid % (g.tx * g.ty);
        const int64_t ty = loc / g.tx, tx = loc % g.tx;
        y0 = T(ty * g.tile) + T(0.5);
        for (int64_t p = 0; p < P; ++p) {
            const int64_t row = ty * g.tile + p / g.tile, col = tx * g.tile + p % g.tile;
            px[p] = T(col) + T(0.5);
            py[p] = T(row) + T(0.5);
            index[p] = (row < g.H && col < g.W) ? (ci * g.H + row) * g.W + col : -1;
        }
    }
};

// Tiles are composited splat by splat, all P pixels of the tile at once
// (branch-free selects, so the pixel loops vectorise); a tile stops early when
// every pixel has reached the transmittance cut-off.
template <typename T>
void composite_fwd(int64_t V, int64_t K, const T* mean2d, const T* conic, const T* opacity, const T* feat,
                   const T* smin, int64_t C, int64_t W, int64_t H, int64_t tile, const int32_t* offsets,
                   const int32_t* isect, T alpha_max, T t_min, T* img, T* t_final, int32_t* n_last) {
    const Grid g(C, W, H, tile);
    (void)V;
    const int64_t P = tile * tile;
    TilePixels<T> pix;
    std::vector<T> Tr(P), acc(K * P), done(P), wv(P);
    std::vector<int32_t> last(P);
    for (int64_t tid = 0; tid < g.n_tiles(); ++tid) {
        pix.set(g, tid);
        const int32_t* ids = isect + offsets[tid];
        const int64_t L = offsets[tid + 1] - offsets[tid];
        std::fill(Tr.begin(), Tr.end(), T(1));
        std::fill(acc.begin(), acc.end(), T(0));
        std::fill(last.begin(), last.end(), 0);
        int64_t n_done = 0;
        for (int64_t p = 0; p < P; ++p) {
            done[p] = pix.index[p] < 0 ? T(1) : T(0);
            n_done += pix.index[p] < 0;
        }
        for (int64_t i = 0; i < L && n_done < P; ++i) {
            const SplatRule<T> s(ids[i], mean2d, conic, opacity, smin);
            const T* f = feat + K * ids[i];
            const T* __restrict px = pix.px.data();
            const T* __restrict py = pix.py.data();
            T* __restrict tr = Tr.data();
            T* __restrict dn = done.data();
            int32_t* __restrict ls = last.data();
            T* __restrict wp = wv.data();  // this splat's weight at every pixel
            int64_t newly = 0, pb, pe;
            s.rows(pix.y0, tile, pb, pe);
            for (int64_t p = pb; p < pe; ++p) {
                const T dx = px[p] - s.mx, dy = py[p] - s.my;
                const T rel = s.rel0 - quad(s.a, s.b, s.c, dx, dy);
                const T al = std::min(vexp(std::max(rel, T(-90))) * s.esmin, alpha_max);
                const bool in = (rel > T(0)) & (dn[p] == T(0));
                const T nt = tr[p] * (T(1) - al);
                const bool stop = in & (t_min > T(0)) & (nt <= t_min);
                const bool use = in & !stop;
                wp[p] = use ? al * tr[p] : T(0);
                tr[p] = use ? nt : tr[p];
                ls[p] = use ? int32_t(i + 1) : ls[p];
                dn[p] = stop ? T(1) : dn[p];
                newly += stop;
            }
            n_done += newly;
            for (int64_t k = 0; k < K; ++k) {
                T* __restrict ak = acc.data() + k * P;
                const T fk = f[k];
                for (int64_t p = pb; p < pe; ++p) ak[p] += wp[p] * fk;
            }
        }
        for (int64_t p = 0; p < P; ++p) {
            const int64_t q = pix.index[p];
            if (q < 0) continue;
            for (int64_t k = 0; k < K; ++k) img[K * q + k] = acc[k * P + p];
            t_final[q] = Tr[p];
            n_last[q] = last[p];
        }
    }
}

template <typename T>
void composite_bwd(int64_t V, int64_t K, const T* mean2d, const T* conic, const T* opacity, const T* feat,
                   const T* smin, int64_t C, int64_t W, int64_t H, int64_t tile, const int32_t* offsets,
                   const int32_t* isect, T alpha_max, const T* grad_img, const T* t_final,
                   const int32_t* n_last, T* grad) {
    const Grid g(C, W, H, tile);
    (void)V;
    const int64_t P = tile * tile;
    const int64_t NG = 6 + K;
    TilePixels<T> pix;
    std::vector<T> Tr(P), suffix(P), Gp(K * P), wv(P), gv(P), lastf(P);
    for (int64_t tid = 0; tid < g.n_tiles(); ++tid) {
        const int64_t L = offsets[tid + 1] - offsets[tid];
        if (L == 0) continue;
        pix.set(g, tid);
        const int32_t* ids = isect + offsets[tid];
        bool any = false;
        int32_t max_last = 0;
        for (int64_t p = 0; p < P; ++p) {
            const int64_t q = pix.index[p];
            if (q < 0) {
                for (int64_t k = 0; k < K; ++k) Gp[k * P + p] = T(0);
                Tr[p] = T(1);
                lastf[p] = T(0);
                continue;
            }
            for (int64_t k = 0; k < K; ++k) {
                Gp[k * P + p] = grad_img[K * q + k];
                any |= grad_img[K * q + k] != T(0);
            }
            Tr[p] = t_final[q];
            lastf[p] = T(n_last[q]);
            max_last = std::max(max_last, n_last[q]);
        }
        if (!any) continue;
        std::fill(suffix.begin(), suffix.end(), T(0));
        for (int64_t i = max_last - 1; i >= 0; --i) {
            const SplatRule<T> s(ids[i], mean2d, conic, opacity, smin);
            const T* f = feat + K * ids[i];
            const T* __restrict px = pix.px.data();
            const T* __restrict py = pix.py.data();
            T* __restrict tr = Tr.data();
            T* __restrict sf = suffix.data();
            const T* __restrict lf = lastf.data();
            T* __restrict w = wv.data();
            T r_mx = 0, r_my = 0, r_a = 0, r_b = 0, r_c = 0, r_o = 0;
            const T fi = T(i);
            int64_t pb, pe;
            s.rows(pix.y0, tile, pb, pe);
            if (pb >= pe) continue;
            T* __restrict gp = gv.data();  // g_p = G_p . f_i
            for (int64_t p = pb; p < pe; ++p) gp[p] = T(0);
            for (int64_t k = 0; k < K; ++k) {
                const T* __restrict Gk = Gp.data() + k * P;
                const T fk = f[k];
                for (int64_t p = pb; p < pe; ++p) gp[p] += Gk[p] * fk;
            }
#pragma omp simd reduction(+ : r_mx, r_my, r_a, r_b, r_c, r_o)
            for (int64_t p = pb; p < pe; ++p) {
                const T dx = px[p] - s.mx, dy = py[p] - s.my;
                const T rel = s.rel0 - quad(s.a, s.b, s.c, dx, dy);
                const T al = std::min(vexp(std::max(rel, T(-90))) * s.esmin, alpha_max);
                const bool use = (rel > T(0)) & (fi < lf[p]);
                const T one_m = T(1) - (use ? al : T(0));
                const T Ti = tr[p] / one_m;  // transmittance in front of splat i
                const T wi = use ? al * Ti : T(0);
                const T ds = (use & (al < alpha_max)) ? (Ti * gp[p] - sf[p] / one_m) * al : T(0);
                r_mx += ds * (s.a * dx + s.b * dy);
                r_my += ds * (s.b * dx + s.c * dy);
                r_a += ds * dx * dx;
                r_b += ds * dx * dy;
                r_c += ds * dy * dy;
                r_o += ds;
                sf[p] += wi * gp[p];
                tr[p] = Ti;
                w[p] = wi;
            }
            T* dst = grad + NG * ids[i];
            dst[0] += r_mx;
            dst[1] += r_my;
            dst[2] += T(-0.5) * r_a;
            dst[3] += -r_b;
            dst[4] += T(-0.5) * r_c;
            dst[5] += r_o / s.opac;
            for (int64_t k = 0; k < K; ++k) {
                const T* __restrict Gk = Gp.data() + k * P;
                T rk = 0;
#pragma omp simd reduction(+ : rk)
                for (int64_t p = pb; p < pe; ++p) rk += w[p] * Gk[p];
                dst[6 + k] += rk;
            }
        }
    }
}

}  // namespace

#define SOMA_RASTER_EXPORT(T, SUF)                                                                        \
    extern "C" int64_t soma_project_##SUF(                                                                \
        int64_t N, int64_t C, const T* means, const T* covs, const T* opac, const T* w2c, const T* Kmat,  \
        int64_t W, int64_t H, T near_plane, T far_plane, T eps2d, T sigma_cutoff, T alpha_min,           \
        int clamp_jac, int64_t* cam_out, int64_t* sidx_out, T* mean2d, T* conic, T* cov2d, T* depth,      \
        T* opac_out, T* smin_out, T* pmax_out) {                                                          \
        return project<T>(N, C, means, covs, opac, w2c, Kmat, W, H, near_plane, far_plane, eps2d,         \
                          sigma_cutoff, alpha_min, clamp_jac, cam_out, sidx_out, mean2d, conic, cov2d,    \
                          depth, opac_out, smin_out, pmax_out);                                           \
    }                                                                                                     \
    extern "C" void soma_project_bwd_##SUF(                                                               \
        int64_t V, const int64_t* cam, const int64_t* sidx, const T* means, const T* covs, const T* w2c,   \
        const T* Kmat, int64_t W, int64_t H, int clamp_jac, const T* conic, const T* g_mean2d,            \
        const T* g_conic, const T* g_depth, const T* g_opac, T* g_means, T* g_covs, T* g_opacs) {          \
        project_bwd<T>(V, cam, sidx, means, covs, w2c, Kmat, W, H, clamp_jac, conic, g_mean2d, g_conic,    \
                       g_depth, g_opac, g_means, g_covs, g_opacs);                                        \
    }                                                                                                     \
    extern "C" int64_t soma_bin_count_##SUF(int64_t V, const T* mean2d, const T* conic, const T* cov2d,   \
                                            const T* pmax, const T* depth, const int64_t* cam, int64_t C,  \
                                            int64_t W, int64_t H, int64_t tile, int32_t* order,           \
                                            int32_t* box, int32_t* counts) {                              \
        return bin_count<T>(V, mean2d, conic, cov2d, pmax, depth, cam, C, W, H, tile, order, box, counts); \
    }                                                                                                     \
    extern "C" void soma_bin_fill_##SUF(int64_t V, const T* mean2d, const T* conic, const T* pmax,        \
                                        const int64_t* cam, int64_t C, int64_t W, int64_t H,              \
                                        int64_t tile, const int32_t* order, const int32_t* box,           \
                                        const int32_t* counts, int32_t* offsets, int32_t* isect) {        \
        bin_fill<T>(V, mean2d, conic, pmax, cam, C, W, H, tile, order, box, counts, offsets, isect);      \
    }                                                                                                     \
    extern "C" void soma_composite_fwd_##SUF(                                                             \
        int64_t V, int64_t K, const T* mean2d, const T* conic, const T* opacity, const T* feat,           \
        const T* smin, int64_t C, int64_t W, int64_t H, int64_t tile, const int32_t* offsets,             \
        const int32_t* isect, T alpha_max, T t_min, T* img, T* t_final, int32_t* n_last) {                \
        composite_fwd<T>(V, K, mean2d, conic, opacity, feat, smin, C, W, H, tile, offsets, isect,         \
                         alpha_max, t_min, img, t_final, n_last);                                         \
    }                                                                                                     \
    extern "C" void soma_composite_bwd_##SUF(                                                             \
        int64_t V, int64_t K, const T* mean2d, const T* conic, const T* opacity, const T* feat,           \
        const T* smin, int64_t C, int64_t W, int64_t H, int64_t tile, const int32_t* offsets,             \
        const int32_t* isect, T alpha_max, const T* grad_img, const T* t_final, const int32_t* n_last,    \
        T* grad) {                                                                                        \
        composite_bwd<T>(V, K, mean2d, conic, opacity, feat, smin, C, W, H, tile, offsets, isect,         \
                         alpha_max, grad_img, t_final, n_last, grad);                                     \
    }

SOMA_RASTER_EXPORT(float, f32)
SOMA_RASTER_EXPORT(double, f64)

extern "C" int soma_raster_abi_version() { return 2; }
