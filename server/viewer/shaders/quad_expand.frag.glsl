#version 300 es
// The expansion pass draws nothing (rasterizer discard); WebGL2 still wants a fragment shader.
precision mediump float;
out vec4 f_color;
void main() {
    f_color = vec4(0.0);
}
