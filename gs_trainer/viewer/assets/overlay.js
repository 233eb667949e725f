// Camera frustums of the gaps viewer: line geometry for the training, test and pseudo-view cameras, drawn
// over the splats, and picking a frustum under the mouse.
'use strict';

const GapsOverlay = (() => {
  const M = GapsMath;

  const COLOURS = {
    train: [0.25, 0.55, 1.0],
    test: [1.0, 0.65, 0.1],
    admitted: [0.2, 0.85, 0.3],
    rejected: [0.95, 0.25, 0.25],
    selected: [1.0, 1.0, 1.0],
  };

  // The image corners of `camera` at distance `depth` along its axis, in world space.
  function frustumCorners(camera, depth) {
    const centre = M.centreOf(camera.R, camera.t);
    return [[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]].map(([u, v]) => {
      const local = [(u - camera.cx) / camera.fx * depth, (v - camera.cy) / camera.fy * depth, depth];
      return M.add(M.mulTransposedVec(camera.R, local), centre);
    });
  }

  // Line segments (pairs of points) of a frustum: apex to corners, the image rectangle, and a tick on the
  // top edge marking "up".
  function frustumSegments(camera, depth) {
    const centre = M.centreOf(camera.R, camera.t);
    const c = frustumCorners(camera, depth);
    const segments = [];
    for (let i = 0; i < 4; ++i) segments.push([centre, c[i]], [c[i], c[(i + 1) % 4]]);
    const topMid = M.scale(M.add(c[0], c[1]), 0.5);
    const up = M.scale(M.mulTransposedVec(camera.R, [0, -1, 0]), 0.15 * depth);
    segments.push([c[0], M.add(topMid, up)], [M.add(topMid, up), c[1]]);
    return segments;
  }

  const LINE_VERTEX_SHADER = `#version 300 es
uniform mat4 u_clip;
layout(location = 0) in vec3 a_position;
layout(location = 1) in vec3 a_colour;
out vec3 v_colour;
void main() {
  gl_Position = u_clip * vec4(a_position, 1.0);
  v_colour = a_colour;
}
`;
  const LINE_FRAGMENT_SHADER = `#version 300 es
precision mediump float;
in vec3 v_colour;
out vec4 out_colour;
void main() { out_colour = vec4(v_colour, 1.0); }
`;

  class Lines {
    constructor(gl) {
      this.gl = gl;
      const compile = (type, source) => {
        const s = gl.createShader(type);
        gl.shaderSource(s, source);
        gl.compileShader(s);
        if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`line shader: ${gl.getShaderInfoLog(s)}`);
        return s;
      };
      this.program = gl.createProgram();
      gl.attachShader(this.program, compile(gl.VERTEX_SHADER, LINE_VERTEX_SHADER));
      gl.attachShader(this.program, compile(gl.FRAGMENT_SHADER, LINE_FRAGMENT_SHADER));
      gl.linkProgram(this.program);
      if (!gl.getProgramParameter(this.program, gl.LINK_STATUS))
        throw new Error(`line shader link: ${gl.getProgramInfoLog(this.program)}`);
      this.clipLocation = gl.getUniformLocation(this.program, 'u_clip');
      this.vao = gl.createVertexArray();
      this.buffer = gl.createBuffer();
      gl.bindVertexArray(this.vao);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffer);
      gl.enableVertexAttribArray(0);
      gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 24, 0);
      gl.enableVertexAttribArray(1);
      gl.vertexAttribPointer(1, 3, gl.FLOAT, false, 24, 12);
      gl.bindVertexArray(null);
      this.vertices = 0;
    }

    // items: [{camera, colour}] drawn as frustums of size `depth`.
    set(items, depth) {
      const data = [];
      for (const {camera, colour} of items)
        for (const [a, b] of frustumSegments(camera, depth)) data.push(...a, ...colour, ...b, ...colour);
      const gl = this.gl;
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffer);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(data), gl.STATIC_DRAW);
      this.vertices = data.length / 6;
    }

    draw(view, sceneScale) {
      if (this.vertices === 0) return;
      const gl = this.gl;
      gl.useProgram(this.program);
      gl.uniformMatrix4fv(this.clipLocation, false, M.clipMatrix(view, 1e-3 * sceneScale, 1e4 * sceneScale));
      gl.bindVertexArray(this.vao);
      gl.drawArrays(gl.LINES, 0, this.vertices);
      gl.bindVertexArray(null);
    }
  }

  // The camera of `items` whose frustum (apex or image-rectangle centre) projects nearest to the pixel, within
  // `radius` pixels; null if none.
  function pick(items, view, depth, pixel, radius) {
    let best = null, bestDistance = radius;
    const project = (p) => {
      const q = M.add(M.mulVec(view.R, p), view.t);
      if (q[2] <= 1e-6) return null;
      return [view.fx * q[0] / q[2] + view.cx, view.fy * q[1] / q[2] + view.cy];
    };
    for (const item of items) {
      const corners = frustumCorners(item.camera, depth);
      const middle = M.scale(corners.reduce(M.add), 0.25);
      for (const p of [M.centreOf(item.camera.R, item.camera.t), middle]) {
        const s = project(p);
        if (!s) continue;
        const d = Math.hypot(s[0] - pixel[0], s[1] - pixel[1]);
        if (d < bestDistance) {
          bestDistance = d;
          best = item;
        }
      }
    }
    return best;
  }

  return {COLOURS, Lines, pick, frustumCorners};
})();
