#version 330 core
// Terrain vertex shader. Positions arrive relative to the tile origin (float32, metres) and the tile
// origin relative to the eye is a per-draw uniform computed in float64 on the CPU, so UTM-sized
// coordinates keep centimetre precision on the GPU.
uniform mat4 u_view_proj;        // view-projection with the eye at the origin
uniform vec3 u_tile_offset;      // tile origin - eye, metres
uniform float u_z_exaggeration;
in vec3 in_position;             // metres, relative to the tile origin
in vec3 in_normal;
out vec3 v_normal;
out vec3 v_rel;                  // position relative to the eye, metres
out float v_height;              // elevation, metres
uniform float u_origin_z;
void main() {
    vec3 p = in_position + u_tile_offset;
    p.z *= u_z_exaggeration;
    v_rel = p;
    v_height = in_position.z + u_origin_z;
    v_normal = normalize(vec3(in_normal.xy * u_z_exaggeration, in_normal.z));
    gl_Position = u_view_proj * vec4(p, 1.0);
}
