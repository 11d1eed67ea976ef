#version 430
// One triangle per splat circumscribing its ellipse, splats read back to front from the order buffer.
layout(std430, binding = 4) readonly buffer Projected { vec4 projected[]; };
layout(std430, binding = 5) readonly buffer Order { uint order[]; };
out vec4 v_color;
out vec2 v_sigma;
const float GUARD = 64.0;  // NDC units: farther than this a triangle's corners are moved onto the viewport
void main() {
    // one triangle per splat, circumscribing the ellipse's unit circle; splats back to front
    uint splat_id = order[uint(gl_VertexID) / 3u];
    int k = gl_VertexID % 3;
    vec2 corner = k == 0 ? vec2(0.0, 2.0) : vec2(k == 1 ? -1.7320508 : 1.7320508, -1.0);
    vec4 center = projected[3u * splat_id];
    if (center.w == 0.0) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
        v_color = vec4(0.0);
        v_sigma = vec2(10.0);
        return;
    }
    vec4 axes = projected[3u * splat_id + 1u];
    v_color = projected[3u * splat_id + 2u];
    v_sigma = center.w * corner;
    gl_Position = vec4(center.xy + corner.x * axes.xy + corner.y * axes.zw, 0.0, 1.0);
    float span = max(max(abs(axes.x), abs(axes.y)), max(abs(axes.z), abs(axes.w)));
    if (max(abs(center.x), abs(center.y)) + 3.0 * span > GUARD) {
        // a huge splat (radii of millions of pixels): its σ-coordinates, interpolated across a triangle
        // that much larger than the screen, came out in straight-edged blocks. It is drawn on a
        // triangle just covering the viewport instead, σ mapped back from there through its axes
        // (in units of the longest, so the 2x2 inverse stays in float32's range).
        vec2 cover = k == 0 ? vec2(-1.0, -1.0) : (k == 1 ? vec2(3.0, -1.0) : vec2(-1.0, 3.0));
        mat2 unit_axes = mat2(axes.xy / span, axes.zw / span);
        if (determinant(unit_axes) == 0.0) {
            gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
            v_color = vec4(0.0);
            return;
        }
        v_sigma = center.w * (inverse(unit_axes) * ((cover - center.xy) / span));
        gl_Position = vec4(cover, 0.0, 1.0);
    }
}
