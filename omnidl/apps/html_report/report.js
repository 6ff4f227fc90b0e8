// omnidl report.html: metrics table, per-image cards sortable by any metric, a panorama viewer (2-D canvas,
// perspective view of an equirectangular image) and a point-cloud viewer (three.js, a 2-D canvas without WebGL) with
// the predicted and ground-truth layout wireframes over the cloud. Every string of the run reaches the document
// through textContent / setAttribute only (never innerHTML).
(function () {
  "use strict";
  var data = JSON.parse(document.getElementById("report-data").textContent);
  var $ = function (id) { return document.getElementById(id); };
  function fmt(v) {
    if (typeof v !== "number" || !isFinite(v)) return v === null || v === undefined ? "" : String(v);
    var a = Math.abs(v);
    return a !== 0 && (a < 1e-3 || a >= 1e5) ? v.toExponential(3) : v.toFixed(4);
  }
  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) { e.setAttribute(k, attrs[k]); });
    if (text !== undefined) e.textContent = text;
    return e;
  }

  // ---- summary and metrics --------------------------------------------------------------------------------
  $("summary").textContent = [data.images.length + " images", "split " + data.split,
    data.checkpoint ? "checkpoint " + data.checkpoint : "untrained model", data.run_dir].join(" \u00b7 ");
  document.title = "omnidl evaluation: " + data.run_name;
  (function () {
    // one column per metric (a short, wide table that leaves the viewers on the first screen)
    var t = $("metrics"), keys = Object.keys(data.metrics);
    var head = el("tr"), vals = el("tr");
    head.appendChild(el("th", {}, "metric")); vals.appendChild(el("td", {}, "mean over " + data.images.length + " images"));
    if (!keys.length) vals.appendChild(el("td", {}, "no labels: predictions only"));
    keys.forEach(function (k) { head.appendChild(el("th", {}, k)); vals.appendChild(el("td", {}, fmt(data.metrics[k]))); });
    t.appendChild(head); t.appendChild(vals);
    var rot = data.rotation, angles = Object.keys(rot || {});
    if (!angles.length) return;
    var rt = $("rotation"), mk = Object.keys(rot[angles[0]]);
    rt.hidden = false;
    var h = el("tr"); h.appendChild(el("th", {}, "rotation (deg)"));
    mk.forEach(function (k) { h.appendChild(el("th", {}, k)); }); rt.appendChild(h);
    angles.forEach(function (a) {
      var row = el("tr"); row.appendChild(el("td", {}, a));
      mk.forEach(function (k) { row.appendChild(el("td", {}, fmt(rot[a][k]))); }); rt.appendChild(row);
    });
  })();

  // ---- image cards, sortable ------------------------------------------------------------------------------
  var selected = null;
  var metricKeys = [];
  data.images.forEach(function (im) {
    Object.keys(im.values).forEach(function (k) { if (metricKeys.indexOf(k) < 0) metricKeys.push(k); });
  });
  var sortSel = $("sort-key");
  sortSel.appendChild(el("option", { value: "" }, "order of evaluation"));
  metricKeys.forEach(function (k) { sortSel.appendChild(el("option", { value: k }, k)); });
  if (data.default_sort && metricKeys.indexOf(data.default_sort) >= 0) sortSel.value = data.default_sort;
  $("sort-desc").checked = data.default_desc !== false;

  function card(im) {
    var c = el("div", { "class": "card", id: "card-" + im.index });
    var h = el("h3"); h.appendChild(el("span", {}, im.name)); h.appendChild(el("span", { "class": "stem" }, im.output));
    c.appendChild(h);
    c.appendChild(el("div", { "class": "values" }, Object.keys(im.values).map(function (k) {
      return k + " " + fmt(im.values[k]);
    }).join("   ")));
    if (im.panel) {
      var img = el("img", { src: im.panel, alt: "panels of " + im.name, loading: im.index < 8 ? "eager" : "lazy" });
      img.addEventListener("click", function () { img.classList.toggle("full"); });
      c.appendChild(img);
    } else {
      c.appendChild(el("div", { "class": "missing" }, "no picture (eval.save_images)"));
    }
    c.addEventListener("click", function () { select(im.index, true); });
    return c;
  }
  var cards = {};
  data.images.forEach(function (im) { cards[im.index] = card(im); });
  function render() {
    var key = sortSel.value, desc = $("sort-desc").checked;
    var list = data.images.slice();
    if (key) {
      list.sort(function (a, b) {
        var x = a.values[key], y = b.values[key];
        var bad = function (v) { return typeof v !== "number" || !isFinite(v); };
        if (bad(x) || bad(y)) return bad(x) - bad(y);
        return desc ? y - x : x - y;
      });
    }
    var box = $("cards");
    while (box.firstChild) box.removeChild(box.firstChild);
    list.forEach(function (im) { box.appendChild(cards[im.index]); });
    $("images-count").textContent = list.length + " images" + (key ? ", sorted by " + key : "");
  }
  sortSel.addEventListener("change", render);
  $("sort-desc").addEventListener("change", render);
  render();

  // ---- panorama viewer ------------------------------------------------------------------------------------
  var pano = { canvas: $("pano"), yaw: 0, pitch: 0, fov: 90, src: null, w: 0, h: 0 };
  var withPano = data.images.filter(function (im) { return im.layers && Object.keys(im.layers).length; });
  withPano.forEach(function (im) { $("pano-image").appendChild(el("option", { value: im.index }, im.name)); });
  function loadLayer(im, layer) {
    var url = im && im.layers[layer];
    $("pano-name").textContent = im ? im.name + " (" + layer + ")" : "no panorama saved (eval.save_images)";
    if (!url) { pano.src = null; drawPano(); return; }
    var img = new Image();
    img.onload = function () {
      var c = document.createElement("canvas"); c.width = img.width; c.height = img.height;
      var g = c.getContext("2d"); g.drawImage(img, 0, 0);
      pano.src = g.getImageData(0, 0, img.width, img.height).data; pano.w = img.width; pano.h = img.height;
      drawPano();
    };
    img.src = url;
  }
  function drawPano() {
    var cv = pano.canvas, g = cv.getContext("2d"), W = cv.width, H = cv.height;
    if (!pano.src) { g.fillStyle = "#222"; g.fillRect(0, 0, W, H); return; }
    var out = g.createImageData(W, H), o = out.data, s = pano.src, sw = pano.w, sh = pano.h;
    var f = (W / 2) / Math.tan(pano.fov * Math.PI / 360);
    var cy = Math.cos(pano.yaw), sy = Math.sin(pano.yaw), cp = Math.cos(pano.pitch), sp = Math.sin(pano.pitch);
    for (var y = 0; y < H; y++) {
      for (var x = 0; x < W; x++) {
        // OpenCV camera ray, pitched about x (+pitch looks up) then turned about y (+yaw turns right)
        var dx = (x + 0.5 - W / 2) / f, dy = (y + 0.5 - H / 2) / f, dz = 1;
        var y1 = dy * cp - dz * sp, z1 = dy * sp + dz * cp;
        var x2 = dx * cy + z1 * sy, z2 = -dx * sy + z1 * cy;
        var lon = Math.atan2(x2, z2), lat = Math.atan2(-y1, Math.sqrt(x2 * x2 + z2 * z2));
        // bilinear read, wrapping in longitude (pixel centres at +0.5)
        var fu = (lon / (2 * Math.PI) + 0.5) * sw - 0.5, fv = Math.min(Math.max((0.5 - lat / Math.PI) * sh - 0.5, 0), sh - 1);
        var u0 = Math.floor(fu), v0 = Math.floor(fv), au = fu - u0, av = fv - v0;
        var ua = ((u0 % sw) + sw) % sw, ub = (ua + 1) % sw, vb = Math.min(v0 + 1, sh - 1);
        var i00 = (v0 * sw + ua) * 4, i01 = (v0 * sw + ub) * 4, i10 = (vb * sw + ua) * 4, i11 = (vb * sw + ub) * 4;
        var oi = (y * W + x) * 4;
        for (var ch = 0; ch < 3; ch++) {
          o[oi + ch] = (s[i00 + ch] * (1 - au) + s[i01 + ch] * au) * (1 - av) + (s[i10 + ch] * (1 - au) + s[i11 + ch] * au) * av;
        }
        o[oi + 3] = 255;
      }
    }
    g.putImageData(out, 0, 0);
  }
  function panoImage() {
    var idx = Number($("pano-image").value);
    return withPano.filter(function (im) { return im.index === idx; })[0];
  }
  function refreshLayers() {
    var im = panoImage(), sel = $("pano-layer"), keep = sel.value;
    while (sel.firstChild) sel.removeChild(sel.firstChild);
    Object.keys(im ? im.layers : {}).forEach(function (k) { sel.appendChild(el("option", { value: k }, k)); });
    if (keep && im && im.layers[keep]) sel.value = keep;
    loadLayer(im, sel.value);
  }
  $("pano-image").addEventListener("change", function () { select(Number($("pano-image").value), false); });
  $("pano-layer").addEventListener("change", function () { loadLayer(panoImage(), $("pano-layer").value); });
  $("pano-reset").addEventListener("click", function () { pano.yaw = 0; pano.pitch = 0; pano.fov = 90; drawPano(); });
  (function () {
    var drag = null, cv = pano.canvas;
    cv.addEventListener("pointerdown", function (e) { drag = [e.clientX, e.clientY]; cv.setPointerCapture(e.pointerId); });
    cv.addEventListener("pointerup", function () { drag = null; });
    cv.addEventListener("pointermove", function (e) {
      if (!drag) return;
      var k = pano.fov / cv.clientWidth * Math.PI / 180;
      pano.yaw -= (e.clientX - drag[0]) * k; pano.pitch += (e.clientY - drag[1]) * k;
      pano.pitch = Math.max(-Math.PI / 2, Math.min(Math.PI / 2, pano.pitch));
      drag = [e.clientX, e.clientY]; drawPano();
    });
    cv.addEventListener("wheel", function (e) {
      e.preventDefault(); pano.fov = Math.max(20, Math.min(150, pano.fov * Math.exp(e.deltaY * 0.001))); drawPano();
    }, { passive: false });
  })();

  // ---- point-cloud viewer ---------------------------------------------------------------------------------
  function decode(b64, Type) {
    var bin = atob(b64), bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return new Type(bytes.buffer);
  }
  var withCloud = data.images.filter(function (im) { return im.cloud || im.layout; });
  withCloud.forEach(function (im) { $("cloud-image").appendChild(el("option", { value: im.index }, im.name)); });
  var view = { az: 0.6, el: 0.5, dist: 6, target: [0, 0, 0], size: 2 };
  var cloud = { pts: null, cols: null, wire: {} };
  // layout wireframes: predicted (green) and ground truth (orange), segment end points in the clouds' y-up frame
  var WIRES = { pred: { color: 0x33ff66, css: "#33ff66", box: "cloud-pred" }, gt: { color: 0xff8c1a, css: "#ff8c1a", box: "cloud-gt" } };
  var box = $("cloud"), webgl = null;
  (function () {
    var probe = document.createElement("canvas");
    var ok = window.THREE && (probe.getContext("webgl2") || probe.getContext("webgl"));
    if (!ok) return;
    var renderer = new THREE.WebGLRenderer({ antialias: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    renderer.setSize(box.clientWidth || 640, box.clientHeight || 360);
    box.appendChild(renderer.domElement);
    var scene = new THREE.Scene(), cam = new THREE.PerspectiveCamera(55, (box.clientWidth || 640) / (box.clientHeight || 360), 0.01, 500);
    scene.background = new THREE.Color(0x222222);
    scene.add(new THREE.AxesHelper(0.5));
    webgl = { renderer: renderer, scene: scene, camera: cam, points: null, lines: {} };
  })();
  var flat = null;
  if (!webgl) { flat = el("canvas", { width: 640, height: 360 }); flat.style.width = "100%"; box.appendChild(flat); }
  function eye() {
    return [view.target[0] + view.dist * Math.cos(view.el) * Math.sin(view.az),
            view.target[1] + view.dist * Math.sin(view.el),
            view.target[2] + view.dist * Math.cos(view.el) * Math.cos(view.az)];
  }
  function drawCloud() {
    if (webgl) {
      if (webgl.points) webgl.points.material.size = view.size * 0.01;
      Object.keys(webgl.lines).forEach(function (k) { webgl.lines[k].visible = $(WIRES[k].box).checked; });
      var e = eye(); webgl.camera.position.set(e[0], e[1], e[2]);
      webgl.camera.lookAt(view.target[0], view.target[1], view.target[2]);
      webgl.renderer.render(webgl.scene, webgl.camera);
      return;
    }
    var g = flat.getContext("2d"), W = flat.width, H = flat.height;
    g.fillStyle = "#222"; g.fillRect(0, 0, W, H);
    var ca = Math.cos(view.az), sa = Math.sin(view.az), ce = Math.cos(view.el), se = Math.sin(view.el);
    var f = H / (2 * Math.tan(27.5 * Math.PI / 180));
    drawPointsFlat(g, W, H, f, ca, sa, ce, se);
    drawWiresFlat(g, W, H, f, ca, sa, ce, se);
  }
  function drawPointsFlat(g, W, H, f, ca, sa, ce, se) {
    if (!cloud.pts) return;
    var n = cloud.pts.length / 3, order = [], proj = new Float32Array(n * 3);
    for (var i = 0; i < n; i++) {
      var x = cloud.pts[3 * i] - view.target[0], y = cloud.pts[3 * i + 1] - view.target[1], z = cloud.pts[3 * i + 2] - view.target[2];
      var xr = x * ca - z * sa, zr = x * sa + z * ca;             // turn about y
      var yr = y * ce - zr * se, zz = y * se + zr * ce;          // tilt about x
      var depth = view.dist - zz;
      if (depth <= 0.05) continue;
      proj[3 * i] = W / 2 + f * xr / depth; proj[3 * i + 1] = H / 2 - f * yr / depth; proj[3 * i + 2] = depth;
      order.push(i);
    }
    order.sort(function (a, b) { return proj[3 * b + 2] - proj[3 * a + 2]; });
    order.forEach(function (i) {
      g.fillStyle = "rgb(" + cloud.cols[3 * i] + "," + cloud.cols[3 * i + 1] + "," + cloud.cols[3 * i + 2] + ")";
      g.fillRect(proj[3 * i], proj[3 * i + 1], view.size, view.size);
    });
  }
  function drawWiresFlat(g, W, H, f, ca, sa, ce, se) {
    function px(p) {
      var x = p[0] - view.target[0], y = p[1] - view.target[1], z = p[2] - view.target[2];
      var xr = x * ca - z * sa, zr = x * sa + z * ca, yr = y * ce - zr * se, zz = y * se + zr * ce;
      var depth = view.dist - zz;
      return depth <= 0.05 ? null : [W / 2 + f * xr / depth, H / 2 - f * yr / depth];
    }
    Object.keys(cloud.wire).forEach(function (k) {
      if (!$(WIRES[k].box).checked) return;
      var s = cloud.wire[k];
      g.strokeStyle = WIRES[k].css; g.lineWidth = 2; g.beginPath();
      for (var i = 0; i + 5 < s.length; i += 6) {
        var a = px([s[i], s[i + 1], s[i + 2]]), b = px([s[i + 3], s[i + 4], s[i + 5]]);
        if (a && b) { g.moveTo(a[0], a[1]); g.lineTo(b[0], b[1]); }
      }
      g.stroke();
    });
  }
  function loadCloud(im) {
    var parts = [];
    if (im && im.cloud) parts.push(im.cloud.n + " of " + im.cloud.total + " points");
    if (im && im.layout) Object.keys(im.layout).forEach(function (k) { parts.push((k === "gt" ? "ground-truth" : "predicted") + " layout"); });
    $("cloud-name").textContent = im ? im.name + " (" + parts.join(", ") + ")"
                                     : "no point cloud or layout saved (eval.save_pointclouds, a layout hook)";
    cloud.pts = im && im.cloud ? decode(im.cloud.xyz, Float32Array) : null;
    cloud.cols = im && im.cloud ? decode(im.cloud.rgb, Uint8Array) : null;
    cloud.wire = {};
    if (im && im.layout) Object.keys(im.layout).forEach(function (k) { if (WIRES[k]) cloud.wire[k] = im.layout[k]; });
    // the view centres on the points, else on the wireframes
    var all = cloud.pts ? cloud.pts : new Float32Array([].concat.apply([], Object.keys(cloud.wire).map(function (k) { return cloud.wire[k]; })));
    var n = all.length / 3, c = [0, 0, 0], r = 0, i, k;
    for (i = 0; i < n; i++) for (k = 0; k < 3; k++) c[k] += all[3 * i + k] / n;
    for (i = 0; i < n; i++) r = Math.max(r, Math.hypot(all[3 * i] - c[0], all[3 * i + 1] - c[1], all[3 * i + 2] - c[2]));
    if (n) { view.target = c; view.dist = Math.max(1, 2.2 * r); }
    if (webgl) {
      if (webgl.points) { webgl.scene.remove(webgl.points); webgl.points.geometry.dispose(); webgl.points.material.dispose(); webgl.points = null; }
      Object.keys(webgl.lines).forEach(function (key) {
        webgl.scene.remove(webgl.lines[key]); webgl.lines[key].geometry.dispose(); webgl.lines[key].material.dispose();
      });
      webgl.lines = {};
      if (cloud.pts) {
        var np = cloud.pts.length / 3, geo = new THREE.BufferGeometry(), cols = new Float32Array(np * 3);
        // the PLY's colours are sRGB; three.js expects linear vertex colours (it converts to sRGB on output)
        for (i = 0; i < np * 3; i++) {
          var s = cloud.cols[i] / 255;
          cols[i] = s <= 0.04045 ? s / 12.92 : Math.pow((s + 0.055) / 1.055, 2.4);
        }
        geo.setAttribute("position", new THREE.BufferAttribute(cloud.pts, 3));
        geo.setAttribute("color", new THREE.BufferAttribute(cols, 3));
        webgl.points = new THREE.Points(geo, new THREE.PointsMaterial({ size: view.size * 0.01, vertexColors: true }));
        webgl.scene.add(webgl.points);
      }
      Object.keys(cloud.wire).forEach(function (key) {
        var lg = new THREE.BufferGeometry();
        lg.setAttribute("position", new THREE.BufferAttribute(new Float32Array(cloud.wire[key]), 3));
        var line = new THREE.LineSegments(lg, new THREE.LineBasicMaterial({ color: WIRES[key].color }));
        webgl.lines[key] = line; webgl.scene.add(line);
      });
    }
    document.body.dataset.wireframes = JSON.stringify(Object.keys(cloud.wire).reduce(function (o, key) {
      o[key] = cloud.wire[key].length / 6; return o; }, {}));
    drawCloud();
  }
  function cloudImage() {
    var idx = Number($("cloud-image").value);
    return withCloud.filter(function (im) { return im.index === idx; })[0];
  }
  $("cloud-image").addEventListener("change", function () { select(Number($("cloud-image").value), false); });
  $("cloud-size").addEventListener("input", function () { view.size = Number($("cloud-size").value); drawCloud(); });
  Object.keys(WIRES).forEach(function (k) { $(WIRES[k].box).addEventListener("change", drawCloud); });
  (function () {
    var drag = null, target = webgl ? webgl.renderer.domElement : flat;
    target.addEventListener("pointerdown", function (e) { drag = [e.clientX, e.clientY]; target.setPointerCapture(e.pointerId); });
    target.addEventListener("pointerup", function () { drag = null; });
    target.addEventListener("pointermove", function (e) {
      if (!drag) return;
      view.az -= (e.clientX - drag[0]) * 0.01;
      view.el = Math.max(-1.5, Math.min(1.5, view.el + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY]; drawCloud();
    });
    target.addEventListener("wheel", function (e) {
      e.preventDefault(); view.dist = Math.max(0.2, view.dist * Math.exp(e.deltaY * 0.001)); drawCloud();
    }, { passive: false });
  })();

  // ---- selection links the cards and the viewers --------------------------------------------------------
  function select(index, fromCard) {
    if (selected !== null && cards[selected]) cards[selected].classList.remove("selected");
    selected = index;
    if (cards[index]) cards[index].classList.add("selected");
    if (withPano.some(function (im) { return im.index === index; })) { $("pano-image").value = index; refreshLayers(); }
    if (withCloud.some(function (im) { return im.index === index; })) { $("cloud-image").value = index; loadCloud(cloudImage()); }
    if (fromCard) $("viewers").scrollIntoView({ behavior: "smooth" });
  }
  refreshLayers();
  loadCloud(cloudImage());
  if (data.images.length) select((withCloud[0] || withPano[0] || data.images[0]).index, false);
  // where the parts are drawn (page coordinates), for tests and screenshots of the page
  var rect = function (e) { var r = e.getBoundingClientRect(); return [r.left + scrollX, r.top + scrollY, r.width, r.height].map(Math.round); };
  function publishLayout() {
    var firstPanel = document.querySelector("#cards img");
    document.body.dataset.layout = JSON.stringify({ pano: rect(pano.canvas), cloud: rect(box),
      panel: firstPanel ? rect(firstPanel) : null, metrics: rect($("metrics")) });
  }
  publishLayout();
  window.addEventListener("load", function () { publishLayout(); document.body.dataset.ready = "yes"; });
  document.body.dataset.viewer3d = webgl ? "webgl" : "canvas2d";
})();
