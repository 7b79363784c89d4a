// The layered quad mesh in WebGL2 (render/quadmesh.py QuadMesh + MeshView). Building, once per applied frame:
// every layer's quad rows go into one instance buffer and shaders/quad_expand.vert.glsl (render/quad.glsl
// inside) turns each quad into 16 vertices, captured by transform feedback -- the compute shader's job, in the
// same buffer layout, so the same 24-index pattern per quad draws them. Drawing, at the display's rate: each
// layer with its camera-to-eye matrix (shaders/quad_mesh.vert/frag.glsl; the cached layer, after a residual frame,
// with the frame's own view too: shaders/quad_mesh_refresh.vert/frag.glsl). The atlas is the decoded VideoFrame,
// uploaded as is (top row first, so uv (0, 0) is its top-left corner, as in the Python client).
import { ROW_FLOATS } from "./quads.js";
import { cameraToWorld, mul, projection, viewMatrix } from "./math.js";

const QUAD_ATTRIBUTES = ["a_head", "a_normal_depth", "a_off0", "a_off1", "a_off2", "a_off3"];
const VERTEX_FLOATS = 5;             // xyz, uv
const VERTICES_PER_QUAD = 16, INDICES_PER_QUAD = 24;
const SUBQUAD_INDICES = [0, 2, 1, 1, 2, 3];   // quad_mesh.comp's order
const MESH_ATTRIBUTES = ["in_position", "in_uv"];   // bound to locations 0, 1 in both mesh programs: one VAO

function compile(gl, type, source, name) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(`${name}: ${gl.getShaderInfoLog(shader)}`);
  return shader;
}

function link(gl, [vs, fs], names, varyings = null, attributes = []) {
  const prog = gl.createProgram();
  gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, vs, names[0]));
  gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, fs, names[1]));
  if (varyings) gl.transformFeedbackVaryings(prog, varyings, gl.INTERLEAVED_ATTRIBS);
  attributes.forEach((name, loc) => gl.bindAttribLocation(prog, loc, name));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(`${names[0]}: ${gl.getProgramInfoLog(prog)}`);
  return prog;
}

// The atlas uv a layer's colour is sampled within: its rect half a texel in (render/quadmesh.py uv_rect).
function uvRect([x, y, w, h], [aw, ah]) {
  return [(x + 0.5) / aw, (y + 0.5) / ah, (x + w - 0.5) / aw, (y + h - 0.5) / ah];
}

function uniforms(gl, prog, names) {
  return Object.fromEntries(names.map((n) => [n, gl.getUniformLocation(prog, n)]));
}

export class MeshRenderer {
  // shaders: {expandVert, expandFrag, meshVert, meshFrag, refreshVert, refreshFrag} sources
  constructor(gl, shaders) {
    this.gl = gl;
    this.expand = link(gl, [shaders.expandVert, shaders.expandFrag], ["quad_expand.vert.glsl", "quad_expand.frag.glsl"],
                       ["v_position", "v_uv"]);
    this.expandU = uniforms(gl, this.expand, ["u_frustum", "u_near", "u_size", "u_atlas_rect", "u_atlas_size"]);
    this.mesh = link(gl, [shaders.meshVert, shaders.meshFrag], ["quad_mesh.vert.glsl", "quad_mesh.frag.glsl"], null,
                     MESH_ATTRIBUTES);
    const meshUniforms = ["u_layer_to_view", "u_proj", "u_depth_scale", "u_max_depth", "u_atlas", "u_uv_rect"];
    this.meshU = uniforms(gl, this.mesh, meshUniforms);
    this.refresh = link(gl, [shaders.refreshVert, shaders.refreshFrag],
                        ["quad_mesh_refresh.vert.glsl", "quad_mesh_refresh.frag.glsl"], null, MESH_ATTRIBUTES);
    this.refreshU = uniforms(gl, this.refresh, [...meshUniforms, "u_layer_to_current", "u_current_rect",
                                                "u_current_uv_rect"]);
    this.current = null;               // {clip: world -> the current view's clip space, rect, uvRect}
    this.quadBuffer = gl.createBuffer();
    this.vertexBuffer = gl.createBuffer();
    this.indexBuffer = gl.createBuffer();
    this.expandVao = gl.createVertexArray();
    this.meshVao = gl.createVertexArray();
    this.feedback = gl.createTransformFeedback();
    this.capacity = 0;
    this.layers = [];                  // {camera, depthScale, first, count, uvRect, layerToWorld, cached}
    this.atlas = gl.createTexture();
    this.atlasSize = null;
    gl.bindTexture(gl.TEXTURE_2D, this.atlas);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  }

  get quadCount() {
    return this.layers.reduce((n, l) => n + l.count, 0);
  }

  _reserve(quads) {
    if (quads <= this.capacity) return;
    const gl = this.gl, cap = Math.max(quads, 2 * this.capacity, 1024);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.quadBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, cap * ROW_FLOATS * 4, gl.DYNAMIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vertexBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, cap * VERTICES_PER_QUAD * VERTEX_FLOATS * 4, gl.DYNAMIC_COPY);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
    const indices = new Uint32Array(cap * INDICES_PER_QUAD);
    for (let q = 0, k = 0; q < cap; q++) {
      for (let s = 0; s < 4; s++) for (const c of SUBQUAD_INDICES) indices[k++] = VERTICES_PER_QUAD * q + 4 * s + c;
    }
    gl.bindVertexArray(this.meshVao);      // the element buffer belongs to the VAO
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.indexBuffer);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vertexBuffer);
    for (const [name, size, offset] of [["in_position", 3, 0], ["in_uv", 2, 12]]) {
      const loc = MESH_ATTRIBUTES.indexOf(name);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, gl.FLOAT, false, VERTEX_FLOATS * 4, offset);
    }
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
    this.capacity = cap;
  }

  // The decoded atlas picture (a VideoFrame, or any TexImageSource) of the frame being applied.
  setAtlas(picture, width, height) {
    const gl = this.gl;
    gl.bindTexture(gl.TEXTURE_2D, this.atlas);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, width, height, 0, gl.RGBA, gl.UNSIGNED_BYTE, picture);
    this.atlasSize = [width, height];
  }

  // Upload and expand the mesh. layers: [{rows, count, camera: layerCamera(), width, height, rect, depthScale}];
  // call after setAtlas (the uv are fractions of the atlas size).
  setLayers(layers) {
    const gl = this.gl, u = this.expandU;
    const total = layers.reduce((n, l) => n + l.count, 0);
    this._reserve(total);
    this.layers = [];
    gl.useProgram(this.expand);
    gl.bindVertexArray(this.expandVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.quadBuffer);
    gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, this.feedback);
    gl.enable(gl.RASTERIZER_DISCARD);
    gl.uniform2f(u.u_atlas_size, this.atlasSize[0], this.atlasSize[1]);
    let first = 0;
    for (const l of layers) {
      if (!l.count) continue;
      gl.bufferSubData(gl.ARRAY_BUFFER, first * ROW_FLOATS * 4, l.rows, 0, l.count * ROW_FLOATS);
      QUAD_ATTRIBUTES.forEach((name, k) => {     // no base instance in WebGL2: point the attributes at the layer
        const loc = gl.getAttribLocation(this.expand, name);
        if (loc < 0) return;
        gl.enableVertexAttribArray(loc);
        gl.vertexAttribPointer(loc, 4, gl.FLOAT, false, ROW_FLOATS * 4, first * ROW_FLOATS * 4 + 16 * k);
        gl.vertexAttribDivisor(loc, 1);
      });
      const f = l.camera.frustum;
      gl.uniform4f(u.u_frustum, f.left, f.right, f.bottom, f.top);
      gl.uniform1f(u.u_near, f.near);
      gl.uniform2i(u.u_size, l.width, l.height);
      gl.uniform4f(u.u_atlas_rect, ...l.rect);
      const bytes = VERTICES_PER_QUAD * VERTEX_FLOATS * 4;
      gl.bindBufferRange(gl.TRANSFORM_FEEDBACK_BUFFER, 0, this.vertexBuffer, first * bytes, l.count * bytes);
      gl.beginTransformFeedback(gl.POINTS);
      gl.drawArraysInstanced(gl.POINTS, 0, VERTICES_PER_QUAD, l.count);
      gl.endTransformFeedback();
      gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, 0, null);
      this.layers.push({ camera: l.camera, depthScale: l.depthScale, first, count: l.count,
                         uvRect: uvRect(l.rect, this.atlasSize),
                         layerToWorld: cameraToWorld(l.camera.position, l.camera.quat), cached: !!l.cached });
      first += l.count;
    }
    gl.disable(gl.RASTERIZER_DISCARD);
    gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, null);
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
  }

  // render/quadmesh.py QuadMesh.set_current_view: until the next call, the cached layers (setLayers' `cached`) are
  // drawn with the colour of the newest frame's own view too (camera: layerCamera(), its rect in this atlas), or
  // with their own alone (null). Call after setAtlas.
  setCurrentView(camera, rect) {
    if (!camera) {
      this.current = null;
      return;
    }
    const [x, y, w, h] = rect, [aw, ah] = this.atlasSize;
    this.current = { clip: mul(projection(camera.frustum), viewMatrix(camera.position, camera.quat)),
                     rect: [x / aw, y / ah, w / aw, h / ah], uvRect: uvRect(rect, this.atlasSize) };
  }

  // Draw the mesh seen through view (world -> eye, column-major) and proj (a projection matrix, or a frustum
  // {left, right, bottom, top, near, far}) into the bound framebuffer's viewport, depth test on; clear first
  // unless told not to (WebXR draws both eyes into one framebuffer).
  draw(view, proj, clear = true) {
    const gl = this.gl, u = this.meshU;
    if (clear) {
      gl.clearColor(0, 0, 0, 0);
      gl.clearDepth(1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    }
    if (!this.layers.length) return;
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.disable(gl.CULL_FACE);
    gl.disable(gl.BLEND);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.atlas);
    const matrix = proj.length ? proj : projection(proj);
    // just inside the far plane (f = m[14] / (m[10] + 1) for a column-major perspective matrix)
    const maxDepth = 0.999 * (proj.length ? matrix[14] / (matrix[10] + 1) : proj.far);
    const current = this.current;
    for (const [prog, pu] of [[this.mesh, u], [this.refresh, this.refreshU]]) {
      gl.useProgram(prog);
      gl.uniform1i(pu.u_atlas, 0);
      gl.uniformMatrix4fv(pu.u_proj, false, new Float32Array(matrix));
      gl.uniform1f(pu.u_max_depth, maxDepth);
    }
    if (current) {
      const r = this.refreshU;
      gl.uniform4f(r.u_current_rect, ...current.rect);
      gl.uniform4f(r.u_current_uv_rect, ...current.uvRect);
    }
    gl.bindVertexArray(this.meshVao);
    for (const layer of this.layers) {
      const refresh = current !== null && layer.cached;
      const pu = refresh ? this.refreshU : u;
      gl.useProgram(refresh ? this.refresh : this.mesh);
      gl.uniform1f(pu.u_depth_scale, layer.depthScale);
      gl.uniform4f(pu.u_uv_rect, ...layer.uvRect);
      gl.uniformMatrix4fv(pu.u_layer_to_view, false, new Float32Array(mul(view, layer.layerToWorld)));
      if (refresh) {
        gl.uniformMatrix4fv(pu.u_layer_to_current, false, new Float32Array(mul(current.clip, layer.layerToWorld)));
      }
      gl.drawElements(gl.TRIANGLES, INDICES_PER_QUAD * layer.count, gl.UNSIGNED_INT, INDICES_PER_QUAD * layer.first * 4);
    }
    gl.bindVertexArray(null);
  }
}
