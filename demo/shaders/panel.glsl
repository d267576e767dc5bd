// One textured quad per panel. Images arrive as linear radiance and are tone mapped here, so the
// CPU hands over raw float data once per frame and the heat map is computed on the GPU from the
// "ours" slot and a reference texture that was uploaded once.
#if defined VERTEX_SHADER
in vec2 in_pos;            // unit quad corners in [0,1]^2
out vec2 uv;
void main() {
    uv = in_pos;
    gl_Position = vec4(in_pos * 2.0 - 1.0, 0.0, 1.0);
}
#elif defined FRAGMENT_SHADER
uniform sampler2D u_image;     // packed panel slots side by side (linear RGB)
uniform sampler2D u_reference; // reference frame (linear RGB), same size as one slot
uniform sampler2D u_overlay;   // RGBA8 text and plot layer
uniform vec2 u_slot;           // (slot index, number of slots) of u_image to show
uniform vec4 u_sub;            // overlay: (u, v, du, dv) of the texture drawn into this viewport
uniform int u_mode;            // 0 tone-mapped image, 1 display-ready image, 2 error heat map, 3 overlay
uniform float u_exposure;
uniform float u_heat_gain;     // heat map saturates at |error| = 1/u_heat_gain (sRGB units)
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

void main() {
    // Textures are stored top row first (numpy order), GL samples bottom-up: flip v.
    vec2 st = vec2(uv.x, 1.0 - uv.y);
    vec2 slot_st = vec2((u_slot.x + st.x) / u_slot.y, st.y);
    if (u_mode == 0) {
        frag = vec4(srgb(texture(u_image, slot_st).rgb * u_exposure), 1.0);
    } else if (u_mode == 1) {
        frag = vec4(clamp(texture(u_image, slot_st).rgb, 0.0, 1.0), 1.0);
    } else if (u_mode == 2) {
        vec3 ours = srgb(texture(u_image, slot_st).rgb * u_exposure);
        vec3 ref = srgb(texture(u_reference, st).rgb * u_exposure);
        float err = dot(abs(ours - ref), vec3(1.0 / 3.0));
        frag = vec4(heat(err * u_heat_gain), 1.0);
    } else {
        frag = texture(u_overlay, u_sub.xy + st * u_sub.zw);
    }
}
#endif
