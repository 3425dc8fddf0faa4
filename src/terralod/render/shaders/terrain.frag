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
    vec3 base = (u_mode == 0) ? texture(u_ramp, vec2(t, 0.5)).rgb : v_tile_colour;
    float diffuse = max(dot(n, u_light_dir), 0.0);
    float shade = 0.35 + 0.65 * diffuse;
    vec3 c = base * shade;
    float fog = 1.0 - exp(-length(v_rel) / max(u_fog_distance, 1.0));
    f_colour = vec4(mix(c, u_fog_colour, fog * 0.85), 1.0);
}
