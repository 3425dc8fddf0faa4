#version 330 core
uniform sampler2D u_text;
in vec2 v_uv;
out vec4 f_colour;
void main() { f_colour = texture(u_text, v_uv); }
