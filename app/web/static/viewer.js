/* MeshMark viewer: a small WebGL view of one indexed triangle mesh, flat shaded, optionally
   coloured by a per-vertex value (the watermark's displacement).  Turn it by dragging or with the
   arrow keys, zoom with the wheel or + / -, reset with 0.  Written for this page: no library. */
"use strict";

(function () {
  const BASE = [0.76, 0.79, 0.83];          // unmarked surface
  // heat ramp, value 0 -> 1: the unmarked grey, then yellow, orange, red, dark red
  const RAMP = [[0.76, 0.79, 0.83], [0.99, 0.85, 0.22], [0.97, 0.52, 0.11], [0.84, 0.15, 0.11],
                [0.45, 0.0, 0.07]];

  function rampGLSL() {
    const n = RAMP.length - 1;
    let body = "vec3 ramp(float t) {\n  t = clamp(t, 0.0, 1.0) * " + n.toFixed(1) + ";\n";
    for (let i = 0; i < n; i++) {
      const a = RAMP[i].map(c => c.toFixed(3)).join(", ");
      const b = RAMP[i + 1].map(c => c.toFixed(3)).join(", ");
      body += "  if (t <= " + (i + 1).toFixed(1) + ") return mix(vec3(" + a + "), vec3(" + b + "), t - " +
        i.toFixed(1) + ");\n";
    }
    return body + "  return vec3(" + RAMP[n].map(c => c.toFixed(3)).join(", ") + ");\n}\n";
  }

  /** CSS colour of the ramp at t in [0, 1] (for the legend). */
  function rampCSS(t) {
    const n = RAMP.length - 1, x = Math.min(Math.max(t, 0), 1) * n, i = Math.min(Math.floor(x), n - 1);
    const f = x - i, c = RAMP[i].map((v, k) => Math.round(255 * (v + (RAMP[i + 1][k] - v) * f)));
    return "rgb(" + c.join(",") + ")";
  }

  function shaders(webgl2) {
    const head = webgl2 ? "#version 300 es\n" : "#extension GL_OES_standard_derivatives : enable\n";
    const vin = webgl2 ? "in" : "attribute", vout = webgl2 ? "out" : "varying";
    const fin = webgl2 ? "in" : "varying";
    const vs = head + vin + " vec3 a_pos;\n" + vin + " float a_val;\nuniform mat4 u_mv, u_proj;\n" +
      vout + " vec3 v_eye;\n" + vout + " float v_val;\n" +
      "void main() {\n  vec4 e = u_mv * vec4(a_pos, 1.0);\n  v_eye = e.xyz;\n  v_val = a_val;\n" +
      "  gl_Position = u_proj * e;\n}\n";
    const fs = head + "precision highp float;\n" + fin + " vec3 v_eye;\n" + fin + " float v_val;\n" +
      (webgl2 ? "out vec4 o_color;\n" : "") + "uniform float u_heat;\n" + rampGLSL() +
      "void main() {\n" +
      "  vec3 n = normalize(cross(dFdx(v_eye), dFdy(v_eye)));\n" +   // flat: the face's own normal
      "  float light = 0.28 + 0.72 * abs(n.z);\n" +                   // a headlight, both sides lit
      "  vec3 base = u_heat > 0.5 ? ramp(v_val) : vec3(" + BASE.join(", ") + ");\n" +
      "  " + (webgl2 ? "o_color" : "gl_FragColor") + " = vec4(base * light, 1.0);\n}\n";
    return [vs, fs];
  }

  function compile(gl, type, source) {
    const s = gl.createShader(type);
    gl.shaderSource(s, source);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s) || "shader");
    return s;
  }

  // column-major 4x4 matrices
  function perspective(fovy, aspect, near, far) {
    const f = 1 / Math.tan(fovy / 2), r = 1 / (near - far);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * r, -1, 0, 0, 2 * far * near * r, 0];
  }

  function orbit(yaw, pitch, distance) {
    // view = translate(0, 0, -distance) * rotateX(pitch) * rotateY(yaw)
    const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
    return [cy, sp * sy, -cp * sy, 0, 0, cp, sp, 0, sy, -sp * cy, cp * cy, 0, 0, 0, -distance, 1];
  }

  class Viewer {
    /** Draws into ``canvas``; ``gl`` is null when the browser has no WebGL (check ``ok``). */
    constructor(canvas) {
      this.canvas = canvas;
      this.mesh = null;
      this.reset();
      const opts = { antialias: true, preserveDrawingBuffer: true };
      let gl = null, webgl2 = false;
      try {
        gl = canvas.getContext("webgl2", opts);
        webgl2 = !!gl;
        if (!gl) {
          gl = canvas.getContext("webgl", opts);
          if (gl && !gl.getExtension("OES_standard_derivatives")) gl = null;
        }
      } catch (e) {
        gl = null;
      }
      this.gl = gl;
      this.webgl2 = webgl2;
      this.ok = !!gl;
      if (!gl) return;
      this.uint32 = webgl2 || !!gl.getExtension("OES_element_index_uint");
      try {
        const [vs, fs] = shaders(webgl2);
        const p = gl.createProgram();
        gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vs));
        gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fs));
        gl.linkProgram(p);
        if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p) || "link");
        this.program = p;
      } catch (e) {
        this.gl = null;
        this.ok = false;
        return;
      }
      this.loc = {
        pos: gl.getAttribLocation(this.program, "a_pos"), val: gl.getAttribLocation(this.program, "a_val"),
        mv: gl.getUniformLocation(this.program, "u_mv"), proj: gl.getUniformLocation(this.program, "u_proj"),
        heat: gl.getUniformLocation(this.program, "u_heat"),
      };
      this.buffers = { pos: gl.createBuffer(), val: gl.createBuffer(), idx: gl.createBuffer() };
      canvas.addEventListener("webglcontextlost", e => { e.preventDefault(); this.ok = false; });
      this._controls();
    }

    reset() {
      this.yaw = -0.6;
      this.pitch = 0.35;
      this.zoom = 1;
      this.redraw();
    }

    /** Shows a mesh: ``positions`` Float32Array (n*3, centred), ``triangles`` Uint32Array (m*3),
        ``values`` Float32Array (n) in [0, 1] or null, ``diagonal`` its size. */
    show(positions, triangles, values, diagonal) {
      if (!this.ok) return false;
      const gl = this.gl;
      if (!this.uint32 && positions.length / 3 > 65535) return false;
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.pos);
      gl.bufferData(gl.ARRAY_BUFFER, positions, gl.STATIC_DRAW);
      if (values) {
        gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.val);
        gl.bufferData(gl.ARRAY_BUFFER, values, gl.STATIC_DRAW);
      }
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.buffers.idx);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, this.uint32 ? triangles : new Uint16Array(triangles),
                    gl.STATIC_DRAW);
      this.mesh = { count: triangles.length, heat: !!values, diagonal: diagonal || 1 };
      this.redraw();
      return true;
    }

    redraw() {
      if (this._pending || !this.gl) return;
      this._pending = true;
      requestAnimationFrame(() => { this._pending = false; this._draw(); });
    }

    _draw() {
      const gl = this.gl, c = this.canvas;
      if (!this.ok || !gl) return;
      const dpr = window.devicePixelRatio || 1;
      const w = Math.max(1, Math.round(c.clientWidth * dpr)), h = Math.max(1, Math.round(c.clientHeight * dpr));
      if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
      gl.viewport(0, 0, w, h);
      gl.clearColor(1, 1, 1, 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      if (!this.mesh) return;
      const d = this.mesh.diagonal, distance = 1.05 * d / this.zoom;
      gl.enable(gl.DEPTH_TEST);
      gl.useProgram(this.program);
      gl.uniformMatrix4fv(this.loc.mv, false, orbit(this.yaw, this.pitch, distance));
      gl.uniformMatrix4fv(this.loc.proj, false,
                          perspective(Math.PI / 4, w / h, distance / 100, distance + 2 * d));
      gl.uniform1f(this.loc.heat, this.mesh.heat ? 1 : 0);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.pos);
      gl.enableVertexAttribArray(this.loc.pos);
      gl.vertexAttribPointer(this.loc.pos, 3, gl.FLOAT, false, 0, 0);
      if (this.mesh.heat && this.loc.val >= 0) {
        gl.bindBuffer(gl.ARRAY_BUFFER, this.buffers.val);
        gl.enableVertexAttribArray(this.loc.val);
        gl.vertexAttribPointer(this.loc.val, 1, gl.FLOAT, false, 0, 0);
      } else if (this.loc.val >= 0) {
        gl.disableVertexAttribArray(this.loc.val);
        gl.vertexAttrib1f(this.loc.val, 0);
      }
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.buffers.idx);
      gl.drawElements(gl.TRIANGLES, this.mesh.count, this.uint32 ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT, 0);
      c.dataset.rendered = String(this.mesh.count / 3);
      c.dataset.heat = this.mesh.heat ? "on" : "off";
    }

    turn(dyaw, dpitch) {
      this.yaw += dyaw;
      this.pitch = Math.max(-1.55, Math.min(1.55, this.pitch + dpitch));
      this.redraw();
    }

    scale(factor) {
      this.zoom = Math.max(0.2, Math.min(50, this.zoom * factor));
      this.redraw();
    }

    _controls() {
      const c = this.canvas;
      let last = null;
      c.addEventListener("pointerdown", e => { last = [e.clientX, e.clientY]; c.setPointerCapture(e.pointerId); });
      c.addEventListener("pointermove", e => {
        if (!last) return;
        this.turn((e.clientX - last[0]) * 0.01, (e.clientY - last[1]) * 0.01);
        last = [e.clientX, e.clientY];
      });
      const stop = () => { last = null; };
      c.addEventListener("pointerup", stop);
      c.addEventListener("pointercancel", stop);
      c.addEventListener("wheel", e => { e.preventDefault(); this.scale(Math.exp(-e.deltaY * 0.0015)); },
                         { passive: false });
      c.addEventListener("keydown", e => {
        const step = e.shiftKey ? 0.5 : 0.15;
        const keys = {
          ArrowLeft: () => this.turn(-step, 0), ArrowRight: () => this.turn(step, 0),
          ArrowUp: () => this.turn(0, -step), ArrowDown: () => this.turn(0, step),
          "+": () => this.scale(1.2), "=": () => this.scale(1.2), "-": () => this.scale(1 / 1.2),
          "0": () => this.reset(), Home: () => this.reset(),
        };
        if (keys[e.key]) { e.preventDefault(); keys[e.key](); }
      });
      window.addEventListener("resize", () => this.redraw());
    }
  }

  window.MeshMarkViewer = { Viewer, rampCSS };
})();
