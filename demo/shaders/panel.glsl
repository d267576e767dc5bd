// The panels, drawn in two passes. Pass 1 (modes 0-2) runs once per image pixel into a small
// framebuffer: it reads the engine's estimates of the whole clip from one texture array (uploaded once
// per iteration, one float plane per layer: layer = (row * 3 + estimate) * 3 + channel), blends the
// two rows around the shown time, tone maps, and computes the error heat map against the reference
// array (uploaded once). Pass 2 (mode 3) magnifies that small image into the window (nearest), so
// the per-fragment work in the window is one texture read. Each pass is its own program (MAGNIFY
// defined for pass 2, MODE for pass 1's three kinds): llvmpipe runs a shader's branches masked, so one program with both would pay
// the tone map for every window pixel.
#if defined VERTEX_SHADER
in vec2 in_pos;            // unit quad corners in [0,1]^2
out vec2 uv;
void main() {
    uv = in_pos;
    gl_Position = vec4(in_pos * 2.0 - 1.0, 0.0, 1.0);
}
#elif defined FRAGMENT_SHADER && defined MAGNIFY
uniform sampler2D u_small;          // pass 1's result
uniform vec4 u_sub;                 // (u, v, du, dv) of u_small drawn into this viewport (v up)
in vec2 uv;
out vec4 frag;
void main() {
    // u_small was drawn by GL (bottom row first) like the window: no flip.
    frag = texture(u_small, u_sub.xy + uv * u_sub.zw);
}
#elif defined FRAGMENT_SHADER
uniform sampler2DArray u_estimates; // engine estimates, planes of (rows, 3 estimates, 3 channels)
uniform sampler2DArray u_reference; // reference frames, planes of (frames, 3 channels)
uniform sampler2D u_view;           // a display-ready feature view (RGB in [0,1])
uniform ivec2 u_rows;               // the two rows around the shown time
uniform float u_blend;              // weight of u_rows.y
uniform int u_estimate;             // which estimate: 0 raw, 1 gaussian, 2 ours
uniform int u_ref_frame;            // reference frame of the shown time (heat map)
// MODE (a define, one program per mode): 0 tone-mapped estimate, 1 feature view, 2 heat map
uniform float u_exposure;
uniform float u_heat_gain;          // heat map saturates at |error| = 1/u_heat_gain (sRGB units)
in vec2 uv;
out vec4 frag;

vec3 srgb(vec3 linear) {
    // Clamped sRGB as the project's PSNR uses it, so what you see is what is scored.
    vec3 c = clamp(linear, 0.0, 1.0);
    return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}

vec3 heat(float x) {
    // Compact "inferno"-like ramp: black -> purple -> orange -> yellow-white.
    x = clamp(x, 0.0, 1.0);
    vec3 a = vec3(0.0, 0.0, 0.02);
    vec3 b = vec3(0.55, 0.05, 0.45);
    vec3 c = vec3(0.98, 0.50, 0.05);
    vec3 d = vec3(1.0, 1.0, 0.75);
    if (x < 0.33) return mix(a, b, x / 0.33);
    if (x < 0.66) return mix(b, c, (x - 0.33) / 0.33);
    return mix(c, d, (x - 0.66) / 0.34);
}

vec3 row_rgb(int row, ivec2 px) {
    int base = (row * 3 + u_estimate) * 3;
    return vec3(texelFetch(u_estimates, ivec3(px, base), 0).r,
                texelFetch(u_estimates, ivec3(px, base + 1), 0).r,
                texelFetch(u_estimates, ivec3(px, base + 2), 0).r);
}

void main() {
    // Pass 1: one fragment per image pixel (the viewport is one panel at image size); the uploaded
    // planes are top row first (numpy order), GL counts rows bottom-up: flip.
    ivec2 size = textureSize(u_estimates, 0).xy;
    ivec2 px = ivec2(uv * vec2(size));
    px.y = size.y - 1 - px.y;  // top row first
#if MODE == 1
    frag = vec4(clamp(texelFetch(u_view, px, 0).rgb, 0.0, 1.0), 1.0);
#else
    vec3 x = mix(row_rgb(u_rows.x, px), row_rgb(u_rows.y, px), u_blend);
#if MODE == 0
    frag = vec4(srgb(x * u_exposure), 1.0);
#else
    {
        int r = u_ref_frame * 3;
        vec3 ref = vec3(texelFetch(u_reference, ivec3(px, r), 0).r, texelFetch(u_reference, ivec3(px, r + 1), 0).r,
                        texelFetch(u_reference, ivec3(px, r + 2), 0).r);
        float err = dot(abs(srgb(x * u_exposure) - srgb(ref * u_exposure)), vec3(1.0 / 3.0));
        frag = vec4(heat(err * u_heat_gain), 1.0);
    }
#endif
#endif
}
#endif
