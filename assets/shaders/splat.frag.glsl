#version 430
// alpha = min(0.99, o exp(-d^2/2)), dropped below 1/255; premultiplied output for ONE, ONE_MINUS_SRC_ALPHA.
in vec4 v_color;
in vec2 v_sigma;
out vec4 frag;
void main() {
    float alpha = min(0.99, v_color.a * exp(-0.5 * dot(v_sigma, v_sigma)));
    if (alpha < 1.0 / 255.0) discard;
    frag = vec4(v_color.rgb * alpha, alpha);
}
