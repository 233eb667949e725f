// The splat renderer of the gaps viewer: decodes a model (the packed format of gs_trainer/viewer/pack.h or an
// antimatter15 .splat file), sorts it by camera depth and draws it with WebGL2 the way the project's
// rasterizer (gs_trainer/raster/raster_math.h, shade_math.h) renders a camera:
//   - the same EWA projection: 3D covariance R S S^T R^T, Jacobian at the mean clamped 0.3 image widths
//     outside the image, 0.3 pixel low-pass dilation, radius 3 sqrt(lambda_max), near plane 0.2;
//   - the same pixels: a splat covers the box of 16x16 tiles around those the rasterizer lists it in (the
//     rect of raster::tile_footprint; the tiles it leaves out have no pixel with alpha >= 1/255), and each
//     pixel centre (i + 0.5, j + 0.5) evaluates alpha = min(0.99, opacity exp(power)), skipped below 1/255;
//   - the same colour: real SH up to degree 3 at the direction from the camera centre, + 0.5, clamped at 0;
//   - the same order: sorted by camera-space z (float), ties by index; composited back to front with the
//     "over" operator, which sums the same weights alpha_i prod_{j<i} (1 - alpha_j) as the rasterizer's front
//     to back loop, over the background. What differs: the rasterizer stops a pixel once its transmittance
//     would fall below 1e-4 (at most 1e-4 of the colour), and float rounding.
// Blending goes to a float render target (32-bit, else 16-bit): 8-bit blending would round every one of
// hundreds of layers. The result is drawn to the canvas, clamped to [0, 1].
'use strict';

const GapsSplats = (() => {
  const SH_C0 = 0.28209479177387814;
  const TEXTURE_WIDTH = 4096;  // texels per row of the data texture (a power of two: index math by shifts)
  const PACK_MAGIC = 'GAPSVW01';

  const halfToFloatTable = (() => {
    let table = null;
    return () => {
      if (table) return table;
      table = new Float32Array(65536);
      for (let h = 0; h < 65536; ++h) {
        const sign = h & 0x8000 ? -1 : 1, exponent = (h >> 10) & 0x1f, mantissa = h & 0x3ff;
        if (exponent === 0) table[h] = sign * mantissa * Math.pow(2, -24);
        else if (exponent === 31) table[h] = mantissa ? NaN : sign * Infinity;
        else table[h] = sign * (1 + mantissa / 1024) * Math.pow(2, exponent - 15);
      }
      return table;
    };
  })();

  // The packed model (pack.h): a 32-byte header ("GAPSVW01", u32 count, u32 SH degree, 16 reserved bytes),
  // then float32 means (3N), scales (3N, activated), quaternions (4N, w x y z), opacities (N, activated),
  // SH DC (3N), and float16 SH rest (3N ((degree + 1)^2 - 1)), all little endian.
  function decodePacked(buffer) {
    const bytes = new Uint8Array(buffer);
    const magic = String.fromCharCode(...bytes.subarray(0, 8));
    if (magic !== PACK_MAGIC) throw new Error(`model: not a gaps packed model (magic '${magic}')`);
    const header = new DataView(buffer, 8, 8);
    const count = header.getUint32(0, true), degree = header.getUint32(4, true);
    if (degree > 3) throw new Error(`model: SH degree ${degree} > 3`);
    const restPer = 3 * ((degree + 1) * (degree + 1) - 1);
    const expected = 32 + count * (4 * (3 + 3 + 4 + 1 + 3) + 2 * restPer);
    if (buffer.byteLength !== expected)
      throw new Error(`model: ${buffer.byteLength} bytes, expected ${expected} for ${count} Gaussians`);
    let offset = 32;
    const floats = (n) => {
      const a = new Float32Array(buffer, offset, n);
      offset += 4 * n;
      return a;
    };
    const model = {count, degree, means: floats(3 * count), scales: floats(3 * count), quats: floats(4 * count),
                   opacities: floats(count), dc: floats(3 * count)};
    const half = new Uint16Array(buffer, offset, restPer * count);
    const table = halfToFloatTable();
    model.rest = new Float32Array(half.length);
    for (let i = 0; i < half.length; ++i) model.rest[i] = table[half[i]];
    return model;
  }

  // antimatter15's .splat: 32 bytes per splat: position 3 x f32, scale 3 x f32 (linear), RGBA u8 (colour
  // 0.5 + C0 dc, opacity), rotation 4 x u8 ((q / |q|) 128 + 128, w first). Degree 0.
  function decodeSplat(buffer) {
    if (buffer.byteLength % 32 !== 0) throw new Error(`.splat: ${buffer.byteLength} bytes, not a multiple of 32`);
    const count = buffer.byteLength / 32;
    const f = new Float32Array(buffer), u = new Uint8Array(buffer);
    const model = {count, degree: 0, means: new Float32Array(3 * count), scales: new Float32Array(3 * count),
                   quats: new Float32Array(4 * count), opacities: new Float32Array(count),
                   dc: new Float32Array(3 * count), rest: new Float32Array(0)};
    for (let i = 0; i < count; ++i) {
      for (let k = 0; k < 3; ++k) {
        model.means[3 * i + k] = f[8 * i + k];
        model.scales[3 * i + k] = f[8 * i + 3 + k];
        model.dc[3 * i + k] = (u[32 * i + 24 + k] / 255 - 0.5) / SH_C0;
      }
      model.opacities[i] = u[32 * i + 27] / 255;
      for (let k = 0; k < 4; ++k) model.quats[4 * i + k] = (u[32 * i + 28 + k] - 128) / 128;
    }
    return model;
  }

  const VERTEX_SHADER = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D u_data;
uniform int u_stride;   // texels per splat
uniform int u_degree;   // SH degree
uniform vec3 u_W0, u_W1, u_W2, u_t;  // world -> camera: rows of R, translation
uniform vec3 u_centre;  // camera centre (world)
uniform vec4 u_K;       // fx, fy, cx, cy (pixels)
uniform vec2 u_size;    // width, height (pixels)
layout(location = 0) in vec2 a_corner;
layout(location = 1) in uint a_index;
flat out vec2 v_mean;
flat out vec3 v_conic;
flat out float v_opacity;
flat out vec3 v_color;

const float kLowPass = 0.3, kNearPlane = 0.2, kFrustumSlack = 0.3, kTile = 16.0;

vec4 fetch(int k) {
  int t = int(a_index) * u_stride + k;
  return texelFetch(u_data, ivec2(t & ${TEXTURE_WIDTH - 1}, t >> ${Math.log2(TEXTURE_WIDTH)}), 0);
}

void cull() { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); }

vec3 shade(vec3 mean) {
  vec3 o = mean - u_centre;
  float dist = length(o);
  vec3 d = o / max(dist, 1e-12);
  float x = d.x, y = d.y, z = d.z;
  float b[16];
  b[0] = 0.28209479177387814;
  b[1] = -0.4886025119029199 * y;
  b[2] = 0.4886025119029199 * z;
  b[3] = -0.4886025119029199 * x;
  float xx = x * x, yy = y * y, zz = z * z;
  b[4] = 1.0925484305920792 * x * y;
  b[5] = -1.0925484305920792 * y * z;
  b[6] = 0.31539156525252005 * (2.0 * zz - xx - yy);
  b[7] = -1.0925484305920792 * x * z;
  b[8] = 0.5462742152960396 * (xx - yy);
  b[9] = -0.5900435899266435 * y * (3.0 * xx - yy);
  b[10] = 2.890611442640554 * x * y * z;
  b[11] = -0.4570457994644658 * y * (4.0 * zz - xx - yy);
  b[12] = 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
  b[13] = -0.4570457994644658 * x * (4.0 * zz - xx - yy);
  b[14] = 1.445305721320277 * z * (xx - yy);
  b[15] = -0.5900435899266435 * x * (xx - 3.0 * yy);
  vec3 color = b[0] * fetch(3).xyz;
  int n = (u_degree + 1) * (u_degree + 1) - 1;
  float rest[48];
  for (int i = 0; i < 12; ++i) {
    if (4 * i >= 3 * n) break;
    vec4 v = fetch(4 + i);
    rest[4 * i] = v.x;
    rest[4 * i + 1] = v.y;
    rest[4 * i + 2] = v.z;
    rest[4 * i + 3] = v.w;
  }
  for (int k = 1; k < 16; ++k) {
    if (k > n) break;
    color += b[k] * vec3(rest[3 * k - 3], rest[3 * k - 2], rest[3 * k - 1]);
  }
  return max(color + 0.5, 0.0);
}

void main() {
  vec4 d0 = fetch(0);
  vec3 mean = d0.xyz;
  float opacity = d0.w;
  vec3 p = vec3(dot(u_W0, mean), dot(u_W1, mean), dot(u_W2, mean)) + u_t;
  if (!(p.z > kNearPlane)) { cull(); return; }
  vec4 q = fetch(2);
  float qnorm = length(q);
  if (!(qnorm > 0.0)) { cull(); return; }
  q /= qnorm;
  float w = q.x, qx = q.y, qy = q.z, qz = q.w;
  vec3 s = fetch(1).xyz;
  // Rows of M = R diag(s); Sigma = M M^T.
  vec3 m0 = vec3(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - w * qz), 2.0 * (qx * qz + w * qy)) * s;
  vec3 m1 = vec3(2.0 * (qx * qy + w * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - w * qx)) * s;
  vec3 m2 = vec3(2.0 * (qx * qz - w * qy), 2.0 * (qy * qz + w * qx), 1.0 - 2.0 * (qx * qx + qy * qy)) * s;
  vec3 s0 = vec3(dot(m0, m0), dot(m0, m1), dot(m0, m2));
  vec3 s1 = vec3(dot(m1, m0), dot(m1, m1), dot(m1, m2));
  vec3 s2 = vec3(dot(m2, m0), dot(m2, m1), dot(m2, m2));

  float fx = u_K.x, fy = u_K.y, cx = u_K.z, cy = u_K.w, W = u_size.x, H = u_size.y;
  float limXPos = (W - cx) / fx + kFrustumSlack * W / fx, limXNeg = cx / fx + kFrustumSlack * W / fx;
  float limYPos = (H - cy) / fy + kFrustumSlack * H / fy, limYNeg = cy / fy + kFrustumSlack * H / fy;
  float ux = clamp(p.x / p.z, -limXNeg, limXPos), uy = clamp(p.y / p.z, -limYNeg, limYPos);
  // Rows of J W, with J = [[fx/z, 0, -fx ux/z], [0, fy/z, -fy uy/z]].
  vec3 t0 = (fx / p.z) * u_W0 + (-fx * ux / p.z) * u_W2;
  vec3 t1 = (fy / p.z) * u_W1 + (-fy * uy / p.z) * u_W2;
  vec3 ts0 = vec3(dot(s0, t0), dot(s1, t0), dot(s2, t0));
  vec3 ts1 = vec3(dot(s0, t1), dot(s1, t1), dot(s2, t1));
  float a = dot(ts0, t0) + kLowPass, b = dot(ts0, t1), c = dot(ts1, t1) + kLowPass;
  float det = a * c - b * b;
  if (!(det > 0.0)) { cull(); return; }
  vec3 conic = vec3(c / det, -b / det, a / det);
  float mid = 0.5 * (a + c);
  float radius = ceil(3.0 * sqrt(mid + sqrt(max(mid * mid - det, 0.1))));
  vec2 m2d = vec2(fx * p.x / p.z + cx, fy * p.y / p.z + cy);
  if (m2d.x + radius <= 0.0 || m2d.x - radius >= W || m2d.y + radius <= 0.0 || m2d.y - radius >= H) {
    cull();
    return;
  }
  // The box of tiles around those the rasterizer lists the splat in: the 3-sigma square, cut to the box
  // outside which alpha < 1/255.
  if (!(opacity * 255.0 >= 1.0 - 1e-6)) { cull(); return; }
  vec2 extent = vec2(radius);
  float cdet = conic.x * conic.z - conic.y * conic.y;
  if (cdet > 0.0) {
    float l = log(255.0 * opacity);
    float r2 = (l > 0.0 ? 2.0 * l : 0.0) * (1.0 + 1e-3) + 1e-4;
    extent = min(extent, vec2(sqrt(r2 * conic.z / cdet), sqrt(r2 * conic.x / cdet)) + 0.5);
  }
  vec2 tiles = ceil(u_size / kTile);
  vec2 lo = clamp(floor((m2d - extent) / kTile), vec2(0.0), tiles);
  vec2 hi = clamp(ceil((m2d + extent) / kTile), vec2(0.0), tiles);
  if (lo.x >= hi.x || lo.y >= hi.y) { cull(); return; }
  vec2 pixel = mix(lo * kTile, min(hi * kTile, u_size), a_corner);
  gl_Position = vec4(2.0 * pixel.x / W - 1.0, 1.0 - 2.0 * pixel.y / H, 0.0, 1.0);
  v_mean = m2d;
  v_conic = conic;
  v_opacity = opacity;
  v_color = shade(mean);
}
`;

  const FRAGMENT_SHADER = `#version 300 es
precision highp float;
uniform vec2 u_size;
flat in vec2 v_mean;
flat in vec3 v_conic;
flat in float v_opacity;
flat in vec3 v_color;
out vec4 out_color;
void main() {
  // Pixel centres (i + 0.5, j + 0.5) with j counted from the top, as the rasterizer's.
  vec2 d = v_mean - vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
  float power = -0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) - v_conic.y * d.x * d.y;
  if (power > 0.0) discard;
  float alpha = min(v_opacity * exp(power), 0.99);
  if (alpha < 1.0 / 255.0) discard;
  out_color = vec4(v_color * alpha, alpha);
}
`;

  const BLIT_VERTEX_SHADER = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}
`;

  const BLIT_FRAGMENT_SHADER = `#version 300 es
precision highp float;
uniform highp sampler2D u_image;
out vec4 out_color;
void main() {
  out_color = vec4(clamp(texelFetch(u_image, ivec2(gl_FragCoord.xy), 0).rgb, 0.0, 1.0), 1.0);
}
`;

  function compile(gl, type, source) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS))
      throw new Error(`shader compilation failed: ${gl.getShaderInfoLog(shader)}`);
    return shader;
  }

  function program(gl, vertexSource, fragmentSource) {
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vertexSource));
    gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fragmentSource));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`shader link failed: ${gl.getProgramInfoLog(p)}`);
    const uniforms = {};
    const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; ++i) {
      const name = gl.getActiveUniform(p, i).name;
      uniforms[name] = gl.getUniformLocation(p, name);
    }
    return {program: p, uniforms};
  }

  // Texels per splat: mean + opacity, scale, quaternion, DC, then the SH rest coefficients, 4 per texel.
  const strideOf = (degree) => 4 + Math.ceil((3 * ((degree + 1) * (degree + 1) - 1)) / 4);

  function packTexture(model) {
    const stride = strideOf(model.degree), restPer = 3 * ((model.degree + 1) * (model.degree + 1) - 1);
    const rows = Math.max(1, Math.ceil((model.count * stride) / TEXTURE_WIDTH));
    const data = new Float32Array(rows * TEXTURE_WIDTH * 4);
    for (let i = 0; i < model.count; ++i) {
      const o = 4 * stride * i;
      data.set(model.means.subarray(3 * i, 3 * i + 3), o);
      data[o + 3] = model.opacities[i];
      data.set(model.scales.subarray(3 * i, 3 * i + 3), o + 4);
      data.set(model.quats.subarray(4 * i, 4 * i + 4), o + 8);
      data.set(model.dc.subarray(3 * i, 3 * i + 3), o + 12);
      data.set(model.rest.subarray(restPer * i, restPer * (i + 1)), o + 16);
    }
    return {data, rows, stride};
  }

  // Stable LSD radix sort of the indices 0..n-1 by float32 key, ascending: ties keep index order.
  function sortByKey(keys, order, scratch) {
    const n = keys.length;
    const bits = new Uint32Array(keys.buffer, keys.byteOffset, n);
    const sortable = new Uint32Array(n);
    for (let i = 0; i < n; ++i) {
      const k = bits[i];
      sortable[i] = k & 0x80000000 ? ~k >>> 0 : (k | 0x80000000) >>> 0;
      order[i] = i;
    }
    const counts = new Uint32Array(256);
    let src = order, dst = scratch;
    for (let shift = 0; shift < 32; shift += 8) {
      counts.fill(0);
      for (let i = 0; i < n; ++i) ++counts[(sortable[src[i]] >>> shift) & 255];
      let total = 0;
      for (let b = 0; b < 256; ++b) {
        const c = counts[b];
        counts[b] = total;
        total += c;
      }
      for (let i = 0; i < n; ++i) dst[counts[(sortable[src[i]] >>> shift) & 255]++] = src[i];
      [src, dst] = [dst, src];
    }
    return src;  // after 4 passes: `order` again
  }

  class Renderer {
    constructor(gl) {
      this.gl = gl;
      this.splatProgram = program(gl, VERTEX_SHADER, FRAGMENT_SHADER);
      this.blitProgram = program(gl, BLIT_VERTEX_SHADER, BLIT_FRAGMENT_SHADER);
      // Float blending: 32-bit where the implementation blends it, else 16-bit.
      const colorFloat = gl.getExtension('EXT_color_buffer_float');
      const floatBlend = gl.getExtension('EXT_float_blend');
      this.targetFormat = colorFloat && floatBlend ? 'RGBA32F' : colorFloat ? 'RGBA16F' : 'RGBA8';
      if (this.targetFormat === 'RGBA8') console.warn('gaps viewer: no float render target; blending in 8 bits');
      this.vao = gl.createVertexArray();
      gl.bindVertexArray(this.vao);
      this.cornerBuffer = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, this.cornerBuffer);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([0, 0, 1, 0, 0, 1, 1, 1]), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(0);
      gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
      this.indexBuffer = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
      gl.enableVertexAttribArray(1);
      gl.vertexAttribIPointer(1, 1, gl.UNSIGNED_INT, 0, 0);
      gl.vertexAttribDivisor(1, 1);
      gl.bindVertexArray(null);
      this.emptyVao = gl.createVertexArray();
      this.model = null;
      this.target = null;
      this.sortedFor = null;
    }

    setModel(model) {
      const gl = this.gl;
      const {data, rows, stride} = packTexture(model);
      if (rows > gl.getParameter(gl.MAX_TEXTURE_SIZE))
        throw new Error(`model: ${model.count} Gaussians exceed this GPU's texture size`);
      if (this.dataTexture) gl.deleteTexture(this.dataTexture);
      this.dataTexture = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, this.dataTexture);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, TEXTURE_WIDTH, rows, 0, gl.RGBA, gl.FLOAT, data);
      this.model = model;
      this.stride = stride;
      this.depths = new Float32Array(model.count);
      this.order = new Uint32Array(model.count);
      this.scratch = new Uint32Array(model.count);
      this.drawOrder = new Uint32Array(model.count);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
      gl.bufferData(gl.ARRAY_BUFFER, this.drawOrder.byteLength, gl.DYNAMIC_DRAW);
      this.sortedFor = null;
    }

    // Back to front: the reverse of the rasterizer's (depth, index) order, depth = camera z in float.
    sort(view) {
      const key = [...view.R, ...view.t].join(',');
      if (this.sortedFor === key) return;
      const f = Math.fround, m = this.model.means, n = this.model.count;
      const w0 = f(view.R[6]), w1 = f(view.R[7]), w2 = f(view.R[8]), tz = f(view.t[2]);
      for (let i = 0; i < n; ++i)
        this.depths[i] = f(f(f(f(w0 * m[3 * i]) + f(w1 * m[3 * i + 1])) + f(w2 * m[3 * i + 2])) + tz);
      const order = sortByKey(this.depths, this.order, this.scratch);
      for (let i = 0; i < n; ++i) this.drawOrder[i] = order[n - 1 - i];
      const gl = this.gl;
      gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
      gl.bufferSubData(gl.ARRAY_BUFFER, 0, this.drawOrder);
      this.sortedFor = key;
    }

    ensureTarget(width, height) {
      const gl = this.gl;
      if (this.target && this.target.width === width && this.target.height === height) return;
      if (this.target) {
        gl.deleteFramebuffer(this.target.framebuffer);
        gl.deleteTexture(this.target.texture);
      }
      const texture = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, texture);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl[this.targetFormat], width, height);
      const framebuffer = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, framebuffer);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
      const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
      if (status !== gl.FRAMEBUFFER_COMPLETE)
        throw new Error(`render target ${this.targetFormat} ${width}x${height} incomplete (${status})`);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      this.target = {texture, framebuffer, width, height};
    }

    // Draws the model seen from `view` ({R, t, centre, fx, fy, cx, cy, width, height}) over `background`
    // (3 values) into the canvas.
    render(view, background) {
      const gl = this.gl;
      this.ensureTarget(view.width, view.height);
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.target.framebuffer);
      gl.viewport(0, 0, view.width, view.height);
      gl.disable(gl.DEPTH_TEST);
      gl.clearColor(background[0], background[1], background[2], 0);
      gl.clear(gl.COLOR_BUFFER_BIT);
      if (this.model && this.model.count > 0) {
        this.sort(view);
        const {program: p, uniforms: u} = this.splatProgram;
        gl.useProgram(p);
        gl.activeTexture(gl.TEXTURE0);
        gl.bindTexture(gl.TEXTURE_2D, this.dataTexture);
        gl.uniform1i(u.u_data, 0);
        gl.uniform1i(u.u_stride, this.stride);
        gl.uniform1i(u.u_degree, this.model.degree);
        gl.uniform3fv(u.u_W0, view.R.slice(0, 3));
        gl.uniform3fv(u.u_W1, view.R.slice(3, 6));
        gl.uniform3fv(u.u_W2, view.R.slice(6, 9));
        gl.uniform3fv(u.u_t, view.t);
        gl.uniform3fv(u.u_centre, view.centre);
        gl.uniform4f(u.u_K, view.fx, view.fy, view.cx, view.cy);
        gl.uniform2f(u.u_size, view.width, view.height);
        gl.enable(gl.BLEND);
        gl.blendFuncSeparate(gl.ONE, gl.ONE_MINUS_SRC_ALPHA, gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
        gl.bindVertexArray(this.vao);
        gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.model.count);
        gl.bindVertexArray(null);
        gl.disable(gl.BLEND);
      }
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, view.width, view.height);
      gl.useProgram(this.blitProgram.program);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.target.texture);
      gl.uniform1i(this.blitProgram.uniforms.u_image, 0);
      gl.bindVertexArray(this.emptyVao);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.bindVertexArray(null);
    }
  }

  return {decodePacked, decodeSplat, Renderer, sortByKey, SH_C0};
})();
