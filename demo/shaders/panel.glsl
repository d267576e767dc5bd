// The panels, drawn in two passes. Pass 1 runs once per image pixel into a small framebuffer holding
// the panels side by side (panel i in columns [i w, (i + 1) w)): it reads the engine's estimates of
// the whole clip from one texture array (uploaded once per iteration, one RGB float layer per row
// and estimate: layer = row * 3 + estimate), blends the two rows around the shown time, tone maps,
// and computes the error heat map against the reference array (uploaded once). Pass 2 (MAGNIFY)
// draws every panel's quad into the window in one call, one interpolated texture read per window
// pixel (llvmpipe's fastest path; a full-window pass that computed each pixel's panel cost 5x more).
// Pass 1 has one program per kind (MODE), and adjacent panels of one kind share a draw: llvmpipe runs
// a shader's branches masked, so one program for all kinds would pay for every kind at every pixel.
// Likewise BLEND: 1 blends two rows (a time between clip frames), 0 reads the one row shown.
#if defined VERTEX_SHADER && defined MAGNIFY
in vec2 in_pos;            // window position in clip space
in vec2 in_uv;             // where it reads pass 1's result
out vec2 uv;
void main() {
    uv = in_uv;
    gl_Position = vec4(in_pos, 0.0, 1.0);
}
#elif defined VERTEX_SHADER
in vec2 in_pos;            // unit quad corners in [0,1]^2
void main() {
    gl_Position = vec4(in_pos * 2.0 - 1.0, 0.0, 1.0);
}
#elif defined FRAGMENT_SHADER && defined MAGNIFY
uniform sampler2D u_small;          // pass 1's result
in vec2 uv;
out vec4 frag;
void main() {
    frag = texture(u_small, uv);
}
#elif defined FRAGMENT_SHADER
uniform sampler2DArray u_estimates; // engine estimates, RGB layers of (rows, 3 estimates)
uniform sampler2DArray u_reference; // reference frames, RGB layers
uniform sampler2D u_view;           // a display-ready feature view (RGB in [0,1])
uniform ivec2 u_rows;               // the two rows around the shown time
uniform float u_blend;              // weight of u_rows.y
uniform int u_estimate[N_PANELS];   // per panel, which estimate: 0 raw, 1 gaussian, 2 ours
uniform int u_ref_frame;            // reference frame of the shown time (heat map)
// MODE (a define, one program per mode): 0 tone-mapped estimate, 1 feature view, 2 heat map
uniform float u_exposure;
uniform float u_heat_gain;          // heat map saturates at |error| = 1/u_heat_gain (sRGB units)
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

vec3 row_rgb(int row, int estimate, ivec2 px) {
    return texelFetch(u_estimates, ivec3(px, row * 3 + estimate), 0).rgb;
}

void main() {
    // The uploaded planes are top row first (numpy order), GL counts rows bottom-up: flip.
    ivec2 size = textureSize(u_estimates, 0).xy;
    ivec2 at = ivec2(gl_FragCoord.xy);
    int panel = int((float(at.x) + 0.5) / float(size.x));  // llvmpipe has no vector integer division
    ivec2 px = ivec2(at.x - panel * size.x, size.y - 1 - at.y);
#if MODE == 1
    frag = vec4(clamp(texelFetch(u_view, px, 0).rgb, 0.0, 1.0), 1.0);
#else
    int estimate = u_estimate[panel];
#if BLEND
    vec3 x = mix(row_rgb(u_rows.x, estimate, px), row_rgb(u_rows.y, estimate, px), u_blend);
#else
    vec3 x = row_rgb(u_rows.x, estimate, px);
#endif
#if MODE == 0
    frag = vec4(srgb(x * u_exposure), 1.0);
#else
    vec3 ref = texelFetch(u_reference, ivec3(px, u_ref_frame), 0).rgb;
    float err = dot(abs(srgb(x * u_exposure) - srgb(ref * u_exposure)), vec3(1.0 / 3.0));
    frag = vec4(heat(err * u_heat_gain), 1.0);
#endif
#endif
}
#endif
