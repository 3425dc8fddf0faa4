#version 330 core
// Terrain vertex shader. Positions arrive relative to the tile origin (float32, metres) and the tile
// origin relative to the eye is computed in float64 on the CPU, so UTM-sized coordinates keep centimetre
// precision on the GPU. Per-tile data is a uniform for plain draws, or (INDIRECT, one multi-draw for the
// whole frame) an instanced attribute selected by each draw command's baseInstance.
uniform mat4 u_view_proj;        // view-projection with the eye at the origin
uniform float u_z_exaggeration;
#ifdef INDIRECT
in vec4 in_tile;                 // xyz: tile origin - eye, metres; w: tile origin z, metres
in vec3 in_colour;               // tile colour (LoD / error modes)
#define TILE_OFFSET in_tile.xyz
#define ORIGIN_Z in_tile.w
#define TILE_COLOUR in_colour
#else
uniform vec3 u_tile_offset;      // tile origin - eye, metres
uniform float u_origin_z;
uniform vec3 u_tile_colour;
#define TILE_OFFSET u_tile_offset
#define ORIGIN_Z u_origin_z
#define TILE_COLOUR u_tile_colour
#endif
in vec3 in_position;             // metres, relative to the tile origin
in vec3 in_normal;
out vec3 v_normal;
out vec3 v_rel;                  // position relative to the eye, metres
out float v_height;              // elevation, metres
flat out vec3 v_tile_colour;
void main() {
    vec3 p = in_position + TILE_OFFSET;
    p.z *= u_z_exaggeration;
    v_rel = p;
    v_height = in_position.z + ORIGIN_Z;
    v_normal = normalize(vec3(in_normal.xy * u_z_exaggeration, in_normal.z));
    v_tile_colour = TILE_COLOUR;
    gl_Position = u_view_proj * vec4(p, 1.0);
}
