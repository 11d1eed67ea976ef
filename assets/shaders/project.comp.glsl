#version 430
// 3DGS preprocessing, one invocation per splat (viewer/renderer.py, docs/viewer.md "How it renders"):
// view transform, EWA projection with the frustum clamp, ellipse axes, SH colour, per-splat style.
// LOCAL_SIZE is #defined by viewer.assets.load_shader.
layout(local_size_x = LOCAL_SIZE) in;
layout(std430, binding = 0) readonly buffer Geometry { vec4 geometry[]; };
layout(std430, binding = 1) readonly buffer Harmonics { float harmonics[]; };
layout(std430, binding = 2) readonly buffer Style { vec4 style[]; };
layout(std430, binding = 3) readonly buffer Ids { uint ids[]; };
layout(std430, binding = 4) writeonly buffer Projected { vec4 projected[]; };

uniform mat3 rotation;
uniform vec3 translation;
uniform vec3 cam_pos;
uniform vec2 focal;
uniform vec2 principal;
uniform vec2 viewport;
uniform vec2 tan_limit_neg;
uniform vec2 tan_limit_pos;
uniform float near_plane;
uniform int coeffs;
uniform uint count;
uniform bool use_ids;
uniform float thin_alpha;
uniform float thin_cov;

const float C0 = 0.28209479177387814;
const float C1 = 0.4886025119029199;
const float C2[5] = float[](1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396);
const float C3[7] = float[](-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658, 1.445305721320277, -0.5900435899266435);

vec3 sh(uint id, int k) {
    uint base = (id * uint(coeffs) + uint(k)) * 3u;
    return vec3(harmonics[base], harmonics[base + 1u], harmonics[base + 2u]);
}

vec3 sh_color(uint id, vec3 d) {
    vec3 c = C0 * sh(id, 0);
    if (coeffs > 1) {
        float x = d.x, y = d.y, z = d.z;
        c += -C1 * y * sh(id, 1) + C1 * z * sh(id, 2) - C1 * x * sh(id, 3);
        if (coeffs > 4) {
            float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
            c += C2[0] * xy * sh(id, 4) + C2[1] * yz * sh(id, 5) + C2[2] * (2.0 * zz - xx - yy) * sh(id, 6)
               + C2[3] * xz * sh(id, 7) + C2[4] * (xx - yy) * sh(id, 8);
            if (coeffs > 9) {
                c += C3[0] * y * (3.0 * xx - yy) * sh(id, 9) + C3[1] * xy * z * sh(id, 10)
                   + C3[2] * y * (4.0 * zz - xx - yy) * sh(id, 11) + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh(id, 12)
                   + C3[4] * x * (4.0 * zz - xx - yy) * sh(id, 13) + C3[5] * z * (xx - yy) * sh(id, 14)
                   + C3[6] * x * (xx - 3.0 * yy) * sh(id, 15);
            }
        }
    }
    return max(c + 0.5, vec3(0.0));
}

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= count) return;
    uint id = use_ids ? ids[i] : i;
    vec4 g0 = geometry[3u * id], g1 = geometry[3u * id + 1u], g2 = geometry[3u * id + 2u];
    vec4 st = style[id];
    // a thinned (moving) subsample keeps 1/f of the splats: 1 - (1 - o)^thin_alpha, thin_alpha = sqrt(f)
    if (thin_alpha != 1.0) g0.w = 1.0 - pow(1.0 - min(g0.w, 0.99), thin_alpha);
    vec3 p = rotation * g0.xyz + translation;
    projected[3u * id] = vec4(0.0);
    if (p.z <= near_plane || st.a < 0.0) return;
    mat3 cov3 = mat3(g1.x, g1.y, g1.z, g1.y, g1.w, g2.x, g1.z, g2.x, g2.y);
    vec2 txy = clamp(p.xy / p.z, -tan_limit_neg, tan_limit_pos) * p.z;
    float iz = 1.0 / p.z;
    mat3 J = mat3(focal.x * iz, 0.0, 0.0,
                  0.0, focal.y * iz, 0.0,
                  -focal.x * txy.x * iz * iz, -focal.y * txy.y * iz * iz, 0.0);
    mat3 T = J * rotation;
    mat3 cov2 = thin_cov * (T * cov3 * transpose(T));
    float a = cov2[0][0] + 0.3, b = cov2[0][1], c = cov2[1][1] + 0.3;
    // the eigen-decomposition in units of the largest entry: squared, the entries of a splat of
    // log-scale ~19 (1e20 px²) pass float32's range, and length() and normalize() gave inf and 0
    float s = max(max(abs(a), abs(c)), abs(b));
    float an = a / s, bn = b / s, cn = c / s;
    float mid = 0.5 * (an + cn);
    float radius = length(vec2(0.5 * (an - cn), bn));
    float l1 = s * (mid + radius), l2 = s * (mid - radius);
    if (!(l2 > 0.0) || isinf(l1)) return;
    vec2 dir = abs(bn) > 1e-12 ? normalize(vec2(bn, mid + radius - an)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
    vec2 uv = focal * p.xy * iz + principal;
    // alpha = o exp(-d²/2) >= 1/255 only within d <= sqrt(2 ln(255 o)) standard deviations
    float reach = min(3.0, sqrt(2.0 * log(max(255.0 * g0.w, 1.0))));
    if (reach <= 0.0) return;
    float extent = reach * sqrt(l1);
    if (uv.x + extent < 0.0 || uv.y + extent < 0.0 || uv.x - extent > viewport.x || uv.y - extent > viewport.y) return;
    vec2 major = reach * sqrt(l1) * dir;
    vec2 minor = reach * sqrt(l2) * vec2(-dir.y, dir.x);
    vec2 to_ndc = vec2(2.0, -2.0) / viewport;
    vec3 rgb = sh_color(id, normalize(g0.xyz - cam_pos));
    rgb = mix(rgb, st.rgb, st.a);
    projected[3u * id] = vec4(uv * to_ndc + vec2(-1.0, 1.0), p.z, reach);
    projected[3u * id + 1u] = vec4(major * to_ndc, minor * to_ndc);
    projected[3u * id + 2u] = vec4(rgb, g0.w);
}
