#version 430
// Progressive path tracer (smallpt economy): diffuse / mirror / glass, emissive spheres and quads as
// lights with next-event estimation, Russian roulette, keyframed translation of objects and camera,
// per-sample time in the shutter interval. One invocation = one pixel of one frame; it loops over its
// samples and writes SUMS (the host divides by spp), so the host reads back once per render.
// HAS_MESH is defined by the host (0/1) so mesh-free scenes compile without the BVH code. The host also
// defines the names shared with Python (tracer.py: shader_defines): feature slots N_FEAT / FEAT_<name>
// (from the feature table, torchmanifold/features.py), material types MAT_*, primitive kinds PRIM_* and
// storage-buffer bindings BIND_*.
layout(local_size_x = 8, local_size_y = 8, local_size_z = 1) in;

#ifndef HAS_MESH
#define HAS_MESH 0
#endif
#ifndef CONST_SCENE
#define CONST_SCENE 0
#endif
// PASS (from the host, tracer.py: PASSES): PASS_STORE / PASS_ACCUMULATE trace samples and store / add their
// sums, PASS_AUX writes the sample-free object ids and motion. Separate programs, not a branch on a uniform:
// llvmpipe executes both sides of every branch, and the additions' loads cost as much as the stores.

const float PI = 3.14159265358979;
const float INF = 1e30;

// Primitive: kind PRIM_SPHERE (a.xyz centre, a.w radius), PRIM_QUAD (a origin, b edge u, c edge v;
// front = u x v), PRIM_MESH (info2.y = BVH root node). info = (kind, material, first keyframe, keyframe count),
// info2 = (is sampled light, bvh root, -, -).
struct Prim { vec4 a; vec4 b; vec4 c; ivec4 info; ivec4 info2; };
// Material: colour.rgb + type (MAT_DIFFUSE, MAT_MIRROR, MAT_GLASS), emission.rgb + index of refraction.
struct Material { vec4 color_type; vec4 emission_ior; };

// output channel of each feature, -1 = not written: constants from the host (OUTPUT_SLOTS), so features
// this tracer does not output are never accumulated and the writes need no per-feature branch
const int feat_slot[N_FEAT] = int[N_FEAT](OUTPUT_SLOTS);

#if CONST_SCENE
// the host pastes the scene here as constant arrays (prims, mats, keys, camkeys, lights) and defines
// N_PRIMS, N_LIGHTS, N_CAMKEYS: llvmpipe then reads plain constants instead of bounds-checked buffers (~2x)
SCENE_CONSTANTS
#else
layout(std430, binding = BIND_PRIMS) readonly buffer Prims { Prim prims[]; };
layout(std430, binding = BIND_MATERIALS) readonly buffer Materials { Material mats[]; };
layout(std430, binding = BIND_KEYS) readonly buffer Keys { vec4 keys[]; };       // (time, offset.xyz)
layout(std430, binding = BIND_CAMKEYS) readonly buffer CamKeys { vec4 camkeys[]; }; // pairs (time, eye), (target, vfov_deg)
layout(std430, binding = BIND_LIGHTS) readonly buffer Lights { int lights[]; };
#define N_PRIMS u_n_prims
#define N_LIGHTS u_n_lights
#define N_CAMKEYS u_n_camkeys
#endif
layout(std430, binding = BIND_TIMES) readonly buffer Times { float frame_times[]; };
layout(std430, binding = BIND_COLOR) buffer OutColor { float out_color[]; };       // (T, 3, H, W) sums
layout(std430, binding = BIND_EMISSION) buffer OutEmission { float out_emission[]; }; // (T, 3, H, W) sums
layout(std430, binding = BIND_FEATURES) buffer OutFeat { float out_feat[]; };         // (T, D, H, W) sums
layout(std430, binding = BIND_AUX) buffer OutAux { float out_aux[]; };           // (T, 3, H, W): id, motion x, y
#if HAS_MESH
layout(std430, binding = BIND_NODES) readonly buffer Nodes { vec4 nodes[]; };  // pairs (bmin, right|first), (bmax, count|-1-axis)
layout(std430, binding = BIND_TRIS) readonly buffer Tris { vec4 tris[]; };    // triples v0, v1, v2
#endif

uniform ivec2 u_size;          // image W, H
uniform ivec2 u_tile_origin;   // pixel offset of this dispatch
uniform ivec2 u_tile_size;
uniform int u_frame_base;      // first frame of this batch of output buffers
uniform int u_n_prims;
uniform int u_n_lights;
uniform int u_n_camkeys;
uniform int u_spp;             // samples in this dispatch
uniform uint u_sample_start;   // global index of the first sample of this dispatch
uniform uint u_seed;
uniform int u_n_feat;          // D
uniform int u_max_depth;
uniform int u_rr_depth;
uniform float u_shutter;
uniform vec3 u_background;
uniform vec3 u_up;

// ---------------------------------------------------------------- RNG (counter based, pcg4d)
uvec4 pcg4d(uvec4 v) {
    v = v * 1664525u + 1013904223u;
    v.x += v.y * v.w; v.y += v.z * v.x; v.z += v.x * v.y; v.w += v.y * v.z;
    v ^= v >> 16u;
    v.x += v.y * v.w; v.y += v.z * v.x; v.z += v.x * v.y; v.w += v.y * v.z;
    return v;
}
uvec4 g_key;
uint g_dim;
// key = (pixel x, pixel y, sample index, frame_key = hash(frame time bits, seed)); each draw hashes its
// dimension in and gives four numbers (pcg4d's four outputs): one hash per four, as call sites draw in fours
void rng_init(uvec2 pix, uint sample_index, uint frame_key) {
    g_key = pcg4d(uvec4(pix.x, pix.y, sample_index, frame_key));
    g_dim = 0u;
}
uint rng_frame_key(float frame_time) {
    return pcg4d(uvec4(floatBitsToUint(frame_time), u_seed, 0x9E3779B9u, 0x85EBCA6Bu)).x;
}
vec4 rnd4() {
    uvec4 h = pcg4d(uvec4(g_key.x, g_key.y, g_key.z ^ g_dim, g_key.w + g_dim * 0x68E31DA4u));
    g_dim += 1u;
    return vec4(h >> 8u) * (1.0 / 16777216.0);
}

// ---------------------------------------------------------------- motion
vec3 prim_offset(int i, float t) {
    int k0 = prims[i].info.z, n = prims[i].info.w;
    if (n == 0) return vec3(0.0);
    if (t <= keys[k0].x || n == 1) return keys[k0].yzw;
    for (int k = k0; k < k0 + n - 1; ++k) {
        if (t <= keys[k + 1].x) {
            float s = (t - keys[k].x) / max(keys[k + 1].x - keys[k].x, 1e-12);
            return mix(keys[k].yzw, keys[k + 1].yzw, s);
        }
    }
    return keys[k0 + n - 1].yzw;
}

struct Camera { vec3 eye; vec3 fwd; vec3 right; vec3 up; float tan_half; float aspect; };
// the segment of keys j, j + 1: t past it takes key j + 1, t inside it interpolates (so keys are held before the
// first and after the last)
#define CAM_SEGMENT(j) { \
    vec4 a0 = camkeys[2 * (j)], a1 = camkeys[2 * (j) + 1], b0 = camkeys[2 * (j) + 2], b1 = camkeys[2 * (j) + 3]; \
    if (t > b0.x) { eye = b0.yzw; target = b1.xyz; fov = b1.w; } \
    else if (t > a0.x) { float s = (t - a0.x) / max(b0.x - a0.x, 1e-12); \
        eye = mix(a0.yzw, b0.yzw, s); target = mix(a1.xyz, b1.xyz, s); fov = mix(a1.w, b1.w, s); } }
Camera camera_at(float t) {
    vec3 eye = camkeys[0].yzw, target = camkeys[1].xyz;
    float fov = camkeys[1].w;
#ifdef FOR_EACH_CAMSEG
    FOR_EACH_CAMSEG(CAM_SEGMENT)  // constant indices: selects of constants, not per-lane reads of the key found
#else
    for (int j = 0; j + 1 < N_CAMKEYS; ++j) CAM_SEGMENT(j)
#endif
    Camera c;
    c.eye = eye;
    c.fwd = normalize(target - eye);
    c.right = normalize(cross(c.fwd, u_up));
    c.up = cross(c.right, c.fwd);
    c.tan_half = tan(radians(fov) * 0.5);
    c.aspect = float(u_size.x) / float(u_size.y);
    return c;
}
// image point (pixels, y down) -> world direction
vec3 camera_dir(Camera c, vec2 p) {
    vec2 ndc = vec2(2.0 * p.x / float(u_size.x) - 1.0, 1.0 - 2.0 * p.y / float(u_size.y));
    return normalize(c.fwd + ndc.x * c.tan_half * c.aspect * c.right + ndc.y * c.tan_half * c.up);
}
vec2 camera_project(Camera c, vec3 p) {
    vec3 v = p - c.eye;
    float z = max(dot(v, c.fwd), 1e-8);
    vec2 ndc = vec2(dot(v, c.right) / (z * c.tan_half * c.aspect), dot(v, c.up) / (z * c.tan_half));
    return vec2((ndc.x + 1.0) * 0.5 * float(u_size.x), (1.0 - ndc.y) * 0.5 * float(u_size.y));
}

// ---------------------------------------------------------------- intersection
// n: geometric normal, front side (outward / u x v). The hit primitive's material and light flag are
// copied in as it is found: with an unrolled scene these are selects of constants, not per-lane gathers.
struct Hit { float t; int prim; vec3 n; Material m; bool light; };
// The tests below are branch-free: llvmpipe runs every branch anyway, and an early return masks all that follows.

float hit_sphere(vec3 o, vec3 d, vec3 c, float r, float tmin) {
    vec3 oc = o - c;
    float b = dot(oc, d);
    vec3 h = oc - b * d;                      // stable discriminant (no huge b*b - c cancellation)
    float disc = r * r - dot(h, h);
    float s = sqrt(max(disc, 0.0));
    float t = -b - s > tmin ? -b - s : -b + s;
    return (disc >= 0.0 && t > tmin) ? t : INF;
}

float hit_quad(vec3 o, vec3 d, vec3 q, vec3 u, vec3 v, float tmin) {
    vec3 n = cross(u, v);
    float den = dot(n, d);
    float t = dot(n, q - o) / den;
    vec3 p = (o - q) + t * d;
    vec3 w = n / dot(n, n);
    float a = dot(p, cross(v, w));  // w . (p x v) = p . (v x w): constant vectors for a baked quad
    float b = dot(p, cross(w, u));
    return (abs(den) >= 1e-12 && t > tmin && min(a, b) >= 0.0 && max(a, b) <= 1.0) ? t : INF;
}

#if HAS_MESH
float hit_tri(vec3 o, vec3 d, vec3 v0, vec3 v1, vec3 v2, float tmin) {
    vec3 e1 = v1 - v0, e2 = v2 - v0;
    vec3 pv = cross(d, e2);
    float det = dot(e1, pv);
    if (abs(det) < 1e-14) return INF;
    float inv = 1.0 / det;
    vec3 tv = o - v0;
    float a = dot(tv, pv) * inv;
    if (a < 0.0 || a > 1.0) return INF;
    vec3 qv = cross(tv, e1);
    float b = dot(d, qv) * inv;
    if (b < 0.0 || a + b > 1.0) return INF;
    float t = dot(e2, qv) * inv;
    return t > tmin ? t : INF;
}
bool hit_box(vec3 o, vec3 inv_d, vec3 bmin, vec3 bmax, float tmax) {
    vec3 t0 = (bmin - o) * inv_d, t1 = (bmax - o) * inv_d;
    vec3 lo = min(t0, t1), hi = max(t0, t1);
    float a = max(max(lo.x, lo.y), max(lo.z, 0.0));
    float b = min(min(hi.x, hi.y), min(hi.z, tmax));
    return a <= b;
}
// nearest triangle of the mesh whose BVH starts at `root` (any one before tmax when any_hit);
// returns t, writes the geometric normal
float hit_mesh(vec3 o, vec3 d, int root, float tmin, float tmax, bool any_hit, out vec3 n) {
    vec3 inv_d = 1.0 / d;
    int stack[32];
    int sp = 0;
    stack[sp++] = root;
    float best = tmax;
    n = vec3(0.0, 1.0, 0.0);
    do {  // do-while, as the tracer's other loops: a loop left at its top costs one more masked pass
        int ni = stack[--sp];
        vec4 a = nodes[2 * ni], b = nodes[2 * ni + 1];
        if (!hit_box(o, inv_d, a.xyz, b.xyz, best)) continue;
        int count = floatBitsToInt(b.w), first = floatBitsToInt(a.w);
        if (count > 0) {
            int j = first;
            do {
                vec3 v0 = tris[3 * j].xyz, v1 = tris[3 * j + 1].xyz, v2 = tris[3 * j + 2].xyz;
                float t = hit_tri(o, d, v0, v1, v2, tmin);
                if (t < best) { best = t; n = cross(v1 - v0, v2 - v0); }
            } while (++j < first + count);
            if (any_hit && best < tmax) break;  // shadow rays need any hit, not the nearest
        } else if (sp < 31) {           // children: ni + 1 (lower along the split axis) and `first`
            bool lower_first = d[-1 - count] >= 0.0;   // the nearer child is popped first: `best` shrinks sooner
            stack[sp++] = lower_first ? first : ni + 1;
            stack[sp++] = lower_first ? ni + 1 : first;
        }
    } while (sp > 0);
    n = normalize(n);
    return best;
}
#endif

// distance to primitive i along (o, d) within (tmin, tmax), INF if none; n = its front normal there
float hit_prim(int i, vec3 o, vec3 d, float tmin, float tmax, float time, bool any_hit, out vec3 n) {
    ivec4 info = prims[i].info;             // read fields as needed: no whole-struct copies per test
    vec3 ro = info.w > 0 ? o - prim_offset(i, time) : o;  // objects only translate: move the ray instead
    n = vec3(0.0);
    float t = INF;
    if (info.x == PRIM_SPHERE) {
        vec4 a = prims[i].a;
        t = hit_sphere(ro, d, a.xyz, a.w, tmin);
        if (t < tmax) n = (ro + t * d - a.xyz) / a.w;
    } else if (info.x == PRIM_QUAD) {
        vec3 u = prims[i].b.xyz, v = prims[i].c.xyz;
        t = hit_quad(ro, d, prims[i].a.xyz, u, v, tmin);
        if (t < tmax) n = normalize(cross(u, v));
    }
#if HAS_MESH
    else {
        t = hit_mesh(ro, d, prims[i].info2.y, tmin, tmax, any_hit, n);
    }
#endif
    return t;
}

void hit_set(inout Hit hit, float t, int i, vec3 n) {
    hit.t = t; hit.prim = i; hit.n = n; hit.m = mats[prims[i].info.y]; hit.light = prims[i].info2.x != 0;
}

bool intersect(vec3 o, vec3 d, float tmin, float tmax, float time, out Hit hit) {
    hit.t = tmax;
    hit.prim = -1;
    hit.n = vec3(0.0);
#ifdef FOR_EACH_PRIM
    // unrolled by the host's FOR_EACH_PRIM: every index is a constant, so each test is specialised to
    // its primitive's kind and numbers (about 3x faster on llvmpipe than the loop, which it does not unroll)
#define INTERSECT_ONE(i) { vec3 n; float t = hit_prim(i, o, d, tmin, hit.t, time, false, n); \
                           if (t < hit.t) { hit_set(hit, t, i, n); } }
    FOR_EACH_PRIM(INTERSECT_ONE)
#else
    for (int i = 0; i < N_PRIMS; ++i) {
        vec3 n;
        float t = hit_prim(i, o, d, tmin, hit.t, time, false, n);
        if (t < hit.t) hit_set(hit, t, i, n);
    }
#endif
    return hit.prim >= 0;
}

// shadow rays: any hit before tmax ends the search. `skip` is the light itself: a convex light cannot hide
// its own sampled point, and testing it would let the ray-origin offset turn the light into its own blocker.
bool occluded(vec3 o, vec3 d, float tmax, float time, int skip) {
#ifdef FOR_EACH_PRIM
#define OCCLUDES(i) { vec3 n; if (i != skip && hit_prim(i, o, d, 0.0, tmax, time, true, n) < tmax) return true; }
    FOR_EACH_PRIM(OCCLUDES)
#else
    for (int i = 0; i < N_PRIMS; ++i) {
        vec3 n;
        if (i != skip && hit_prim(i, o, d, 0.0, tmax, time, true, n) < tmax) return true;
    }
#endif
    return false;
}

// ---------------------------------------------------------------- sampling helpers
void onb(vec3 n, out vec3 t, out vec3 b) {   // Duff et al. 2017
    float s = n.z >= 0.0 ? 1.0 : -1.0;
    float a = -1.0 / (s + n.z);
    float c = n.x * n.y * a;
    t = vec3(1.0 + s * n.x * n.x * a, s * c, -s * n.x);
    b = vec3(c, s + n.y * n.y * a, -n.y);
}
vec3 cosine_dir(vec3 n, float u1, float u2) {
    float r = sqrt(u1), phi = 2.0 * PI * u2;
    vec3 t, b;
    onb(n, t, b);
    return normalize(r * cos(phi) * t + r * sin(phi) * b + sqrt(max(0.0, 1.0 - u1)) * n);
}
float ray_eps(vec3 p) { return 1e-4 * max(1.0, max(abs(p.x), max(abs(p.y), abs(p.z)))); }

float luminance(vec3 c) { return dot(c, vec3(0.2126, 0.7152, 0.0722)); }  // Rec. 709, as the Python side's

// next-event estimation: one light chosen uniformly (by u.x); a sphere light samples the cone of directions
// it subtends, a quad a point uniform on its area (by u.yz). Returns the radiance contribution (already /
// pdf) and the unit shadow-ray direction.
vec3 sample_light_prim(int li, vec3 p, vec3 n, vec3 albedo, float time, vec2 u, out vec3 sdir) {
    Prim lp = prims[li];
    vec3 off = lp.info.w > 0 ? prim_offset(li, time) : vec3(0.0);
    float u1 = u.x, u2 = u.y;
    float dist, inv_pdf;  // inv_pdf = 1 / (solid-angle pdf of sdir)
    sdir = vec3(0.0);
    if (lp.info.x == PRIM_SPHERE) {
        vec3 c = lp.a.xyz + off;
        float r = lp.a.w;
        vec3 wc = c - p;
        float dc2 = dot(wc, wc);
        if (dc2 <= r * r * 1.0001) return vec3(0.0);  // on or inside: spheres emit outward only
        float cos_max = sqrt(max(0.0, 1.0 - r * r / dc2));
        float ct = 1.0 - u1 * (1.0 - cos_max), st = sqrt(max(0.0, 1.0 - ct * ct)), phi = 2.0 * PI * u2;
        vec3 axis = wc * inversesqrt(dc2), t, b;
        onb(axis, t, b);
        sdir = normalize(st * cos(phi) * t + st * sin(phi) * b + ct * axis);
        dist = hit_sphere(p, sdir, c, r, 0.0);
        if (dist >= INF) return vec3(0.0);             // grazing direction lost to rounding
        inv_pdf = 2.0 * PI * (1.0 - cos_max);
    } else {
        vec3 cr = cross(lp.b.xyz, lp.c.xyz);
        float area = length(cr);
        vec3 w = lp.a.xyz + off + u1 * lp.b.xyz + u2 * lp.c.xyz - p;
        float dist2 = dot(w, w);
        dist = sqrt(dist2);
        sdir = w / dist;
        float cos_y = -dot(cr / area, sdir);             // quads emit from the front face only
        if (cos_y <= 0.0) return vec3(0.0);
        inv_pdf = area * cos_y / dist2;
    }
    float cos_x = dot(n, sdir);
    if (cos_x <= 0.0) return vec3(0.0);
    vec3 o = p + n * ray_eps(p);
    if (occluded(o, sdir, dist * (1.0 - 1e-4), time, li)) return vec3(0.0);
    vec3 le = mats[lp.info.y].emission_ior.rgb;
    return le * (albedo / PI) * cos_x * inv_pdf * float(N_LIGHTS);
}

vec3 sample_light(vec3 p, vec3 n, vec3 albedo, float time, vec3 u, out vec3 sdir) {
    int j = min(int(u.x * float(N_LIGHTS)), N_LIGHTS - 1);
#ifdef FOR_EACH_LIGHT
    // one specialised copy per light (constant index), as for FOR_EACH_PRIM
    vec3 r = vec3(0.0);
    sdir = vec3(0.0);
#define SAMPLE_ONE_LIGHT(k) if (j == k) r = sample_light_prim(lights[k], p, n, albedo, time, u.yz, sdir);
    FOR_EACH_LIGHT(SAMPLE_ONE_LIGHT)
    return r;
#else
    return sample_light_prim(lights[j], p, n, albedo, time, u.yz, sdir);
#endif
}

// ---------------------------------------------------------------- main
// this invocation's pixel and frame (index into this batch's output buffers); false outside the tile/image
bool invocation_pixel(out ivec2 pix, out int f) {
    ivec2 local = ivec2(gl_GlobalInvocationID.xy);
    pix = u_tile_origin + local;
    f = int(gl_GlobalInvocationID.z);
    return all(lessThan(local, u_tile_size)) && all(lessThan(pix, u_size));
}

#if PASS == PASS_AUX
// object id and screen-space motion of the pixel-centre first hit at the frame time: sample-free, so the
// host runs this pass only for frame times it has not kept (tracer.py: AUX_CACHE_BYTES), not per render
void main() {
    ivec2 pix;
    int f;
    if (!invocation_pixel(pix, f)) return;
    float ftime = frame_times[u_frame_base + f];
    int plane = u_size.x * u_size.y, base3 = f * 3 * plane + pix.y * u_size.x + pix.x;
    Camera c0 = camera_at(ftime), c1 = camera_at(ftime + 1.0);
    vec2 centre = vec2(pix) + 0.5;
    vec3 d0 = camera_dir(c0, centre);
    Hit h;
    float id = -1.0;
    vec3 p1;
    if (intersect(c0.eye, d0, 0.0, INF, ftime, h)) {
        id = float(h.prim);
        p1 = c0.eye + h.t * d0 + prim_offset(h.prim, ftime + 1.0) - prim_offset(h.prim, ftime);
    } else {
        p1 = c1.eye + d0 * 1e6;                         // direction at infinity: camera rotation only
    }
    vec2 mv = camera_project(c1, p1) - centre;
    out_aux[base3] = id;
    out_aux[base3 + plane] = mv.x;
    out_aux[base3 + 2 * plane] = mv.y;
}
#else
void main() {
    ivec2 pix;
    int f;
    if (!invocation_pixel(pix, f)) return;
    float ftime = frame_times[u_frame_base + f];
    int plane = u_size.x * u_size.y, pidx = pix.y * u_size.x + pix.x;

    vec3 sum_c = vec3(0.0), sum_e = vec3(0.0);
    float feat[N_FEAT];
    for (int k = 0; k < N_FEAT; ++k) feat[k] = 0.0;

    uint frame_key = rng_frame_key(ftime);
    // do-while loops (u_spp, u_max_depth >= 1): a loop that exits at its top runs one more, fully masked pass
    // of its body on llvmpipe (it only leaves a loop when no lane is left at the bottom)
    int s = 0;
    do {
        rng_init(uvec2(pix), u_sample_start + uint(s), frame_key);
        vec4 r = rnd4();  // time, jitter x, y
        float time = ftime + (r.x - 0.5) * u_shutter;
        vec2 jitter = r.yz;
        Camera cam = camera_at(time);
        vec3 o = cam.eye;
        vec3 d = camera_dir(cam, vec2(pix) + jitter);
        vec3 L = vec3(0.0), beta = vec3(1.0);
        bool count_light = true;  // emission of sampled lights counts unless NEE already did
        // caustic light: what reaches a diffuse vertex from a light or the sky through mirrors or glass
        // (after a diffuse vertex, only a specular one sets count_light)
        bool diffuse_seen = false;
        vec3 Lc = vec3(0.0);
        feat[FEAT_T] += time;
        // the first vertex's features, added to the sums after the path: accumulating them inside the bounce
        // loop would cost at every vertex (llvmpipe executes the depth == 0 branches at every one)
        float z1 = 0.0;
        vec3 albedo1 = vec3(0.0), emission1 = vec3(0.0), le1 = vec3(0.0), n1 = vec3(0.0), s1 = vec3(0.0), d1 = vec3(0.0);
        int depth = 0;
        do {
            // this vertex's numbers, drawn whatever it needs: light choice and point, BSDF direction, glass
            // reflect-or-refract, Russian roulette
            vec4 ra = rnd4(), rb = rnd4();
            Hit h;
            if (!intersect(o, d, 0.0, INF, time, h)) {
                L += beta * u_background;
                if (count_light && diffuse_seen) Lc += beta * u_background;
                break;
            }
            Material m = h.m;
            vec3 x = o + h.t * d;
            vec3 nf = dot(h.n, d) < 0.0 ? h.n : -h.n;   // facing the incoming ray
            vec3 le = dot(h.n, d) < 0.0 ? m.emission_ior.rgb : vec3(0.0);  // emitters: outward / front face
            if (count_light || !h.light) L += beta * le;
            if (count_light && diffuse_seen) Lc += beta * le;
            int mtype = int(m.color_type.w);
            vec3 albedo = m.color_type.rgb;
            if (depth == 0) { z1 = h.t; albedo1 = albedo; emission1 = m.emission_ior.rgb; le1 = le; n1 = nf; }
            vec3 nd;
            if (mtype == MAT_DIFFUSE) {
                if (N_LIGHTS > 0) {
                    vec3 sdir;
                    L += beta * sample_light(x, nf, albedo, time, vec3(rb.x, ra.xy), sdir);
                    if (depth == 0) s1 = sdir;
                }
                nd = cosine_dir(nf, ra.z, ra.w);
                beta *= albedo;
                count_light = false;
                diffuse_seen = true;
            } else if (mtype == MAT_MIRROR) {
                nd = reflect(d, nf);
                beta *= albedo;
                count_light = true;
            } else {                                        // MAT_GLASS (exact dielectric Fresnel)
                float ior = m.emission_ior.w;
                bool entering = dot(h.n, d) < 0.0;
                float eta = entering ? 1.0 / ior : ior;
                float ci = -dot(d, nf);
                float s2 = eta * eta * (1.0 - ci * ci);
                float ct = sqrt(max(1.0 - s2, 0.0));       // branch-free: total internal reflection is fr = 1
                float rs = (eta * ci - ct) / (eta * ci + ct);
                float rp = (ci - eta * ct) / (ci + eta * ct);
                float fr = s2 < 1.0 ? 0.5 * (rs * rs + rp * rp) : 1.0;
                if (rb.y < fr) nd = reflect(d, nf);
                else nd = normalize(eta * d + (eta * ci - ct) * nf);
                beta *= albedo;
                count_light = true;
            }
            if (depth == 0) d1 = nd;
            o = x + (dot(nd, nf) > 0.0 ? nf : -nf) * ray_eps(x);
            d = nd;
            if (depth + 1 >= u_rr_depth) {                 // Russian roulette
                float q = min(0.95, max(beta.r, max(beta.g, beta.b)));
                if (q <= 0.0 || rb.z >= q) break;
                beta /= q;
            }
        } while (++depth < u_max_depth);
        sum_c += L;
        sum_e += le1;
        vec3 a = albedo1, e = emission1;  // emitters with black colour: emission / max as albedo
        if (max(a.r, max(a.g, a.b)) <= 0.0 && max(e.r, max(e.g, e.b)) > 0.0) a = e / max(e.r, max(e.g, e.b));
        float lum = luminance(L);
        feat[FEAT_C] += lum > 0.0 ? clamp(luminance(Lc) / lum, 0.0, 1.0) : 0.0;
        feat[FEAT_Z] += z1; feat[FEAT_MR] += a.r; feat[FEAT_MG] += a.g; feat[FEAT_MB] += a.b;
        feat[FEAT_NX] += n1.x; feat[FEAT_NY] += n1.y; feat[FEAT_NZ] += n1.z;
        feat[FEAT_SX] += s1.x; feat[FEAT_SY] += s1.y; feat[FEAT_SZ] += s1.z;
        feat[FEAT_DX] += d1.x; feat[FEAT_DY] += d1.y; feat[FEAT_DZ] += d1.z;
    } while (++s < u_spp);

    // sums: the first chunk of samples stores them, later chunks add to them
    int base3 = f * 3 * plane + pidx, basef = f * u_n_feat * plane + pidx;
#if PASS == PASS_ACCUMULATE
#define OUT(buf, i, v) buf[i] += v
#else
#define OUT(buf, i, v) buf[i] = v
#endif
    for (int c = 0; c < 3; ++c) {
        OUT(out_color, base3 + c * plane, sum_c[c]);
        OUT(out_emission, base3 + c * plane, sum_e[c]);
    }
    for (int k = 0; k < N_FEAT; ++k)
        if (feat_slot[k] >= 0) OUT(out_feat, basef + feat_slot[k] * plane, feat[k]);
}
#endif
