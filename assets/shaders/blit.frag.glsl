#version 330
// Samples the offscreen image (linear filtering when scaled).
uniform sampler2D image;
in vec2 uv;
out vec4 frag;
void main() { frag = vec4(texture(image, uv).rgb, 1.0); }
