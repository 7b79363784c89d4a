#version 430
// Shadow pass: depth only.
void main() {}
