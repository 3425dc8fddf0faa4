#version 330 core
// Elevation colour ramp x hillshade from the vertex normals, with distance fog toward the sky colour.
// Modes: 0 = elevation ramp, 1 = level-of-detail colour (per-tile colour), 2 = error heat-map (per-tile colour),
// 3 = facing diagnostic (front faces white, back faces red: a back face seen on terrain means lost depth).
uniform vec3 u_light_dir;        // unit vector toward the sun
uniform vec2 u_height_range;     // metres, for the ramp
uniform vec3 u_fog_colour;
uniform float u_fog_distance;    // metres at which fog reaches ~63 %
uniform int u_mode;
flat in vec3 v_tile_colour;  // per-tile colour (LoD / error modes)
uniform sampler2D u_ramp;
// change overlay (render/overlay.py): change metres (r) and validity (g) on the store's grid
uniform int u_overlay;           // 1: colour gain / loss over the terrain
uniform sampler2D u_change;
uniform vec2 u_change_origin;    // grid's north-west corner - eye, metres
uniform vec2 u_change_scale;     // (1 / width, -1 / height) of the grid, 1/metres
uniform float u_change_lod;      // |change| below it: greyed out
uniform float u_change_max;      // |change| where the colours saturate
uniform vec3 u_gain_light;
uniform vec3 u_gain_dark;
uniform vec3 u_loss_light;
uniform vec3 u_loss_dark;
uniform vec2 u_water;            // heights drawn as water, metres (lo, hi); none when lo > hi
uniform vec3 u_water_colour;
in vec3 v_normal;
in vec3 v_rel;
in float v_height;
out vec4 f_colour;
void main() {
    if (u_mode == 3) {
        f_colour = gl_FrontFacing ? vec4(1.0) : vec4(1.0, 0.0, 0.0, 1.0);
        return;
    }
    vec3 n = normalize(v_normal);
    if (!gl_FrontFacing) n = -n;
    float t = clamp((v_height - u_height_range.x) / max(u_height_range.y - u_height_range.x, 1e-3), 0.0, 1.0);
    // the ramp's 256 texels are addressed at their centres, so both ends are the end colours
    vec3 base = (u_mode == 0) ? texture(u_ramp, vec2(0.5 / 256.0 + t * 255.0 / 256.0, 0.5)).rgb : v_tile_colour;
    if (u_overlay == 1) {
        vec2 uv = (v_rel.xy - u_change_origin) * u_change_scale;
        vec2 cv = texture(u_change, uv).rg;
        bool inside = all(greaterThanEqual(uv, vec2(0.0))) && all(lessThanEqual(uv, vec2(1.0)));
        if (inside && cv.g > 0.5) {
            float ad = abs(cv.r);
            if (ad < u_change_lod) {
                base = vec3(0.12 + 0.8 * dot(base, vec3(0.299, 0.587, 0.114)));
            } else {
                float k = clamp((ad - u_change_lod) / max(u_change_max - u_change_lod, 1e-6), 0.0, 1.0);
                base = cv.r >= 0.0 ? mix(u_gain_light, u_gain_dark, k) : mix(u_loss_light, u_loss_dark, k);
            }
        }
    }
    float diffuse = max(dot(n, u_light_dir), 0.0);
    float shade = 0.35 + 0.65 * diffuse;
    vec3 c = base * shade;
    if (u_mode == 0 && v_height >= u_water.x && v_height <= u_water.y) c = u_water_colour;
    float fog = 1.0 - exp(-length(v_rel) / max(u_fog_distance, 1.0));
    c = mix(c, u_fog_colour, fog * 0.85);
    // +-1/2 of an 8-bit step of noise: smooth gradients (fog, flat shading) no longer band into rings
    float noise = fract(sin(dot(gl_FragCoord.xy, vec2(12.9898, 78.233))) * 43758.5453);
    f_colour = vec4(c + (noise - 0.5) / 255.0, 1.0);
}
