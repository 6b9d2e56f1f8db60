(function () {
  "use strict";
  var MAX_LIVE = 6;
  var data = JSON.parse(document.getElementById("cm-data").textContent);
  var cache = {};
  var live = [];
  function bytes(b64) {
    var s = atob(b64), u = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
    return u;
  }
  function geometry(key) {
    if (cache[key]) return cache[key];
    var g = data.geometries[key];
    var v = new Uint16Array(bytes(g.positions).buffer), fb = bytes(g.faces).buffer;
    var f = g.index_bits === 16 ? new Uint16Array(fb) : new Uint32Array(fb);
    var out = {x: new Float32Array(g.n), y: new Float32Array(g.n), z: new Float32Array(g.n),
               i: new Uint32Array(g.m), j: new Uint32Array(g.m), k: new Uint32Array(g.m), units: g.units,
               centre: g.centre, neck: g.neck, anterior: g.anterior, regions: g.regions};
    var o = g.origin, s = g.step;
    for (var a = 0; a < g.n; a++) {
      out.x[a] = o[0] + s[0] * v[3 * a]; out.y[a] = o[1] + s[1] * v[3 * a + 1]; out.z[a] = o[2] + s[2] * v[3 * a + 2];
    }
    for (var b = 0; b < g.m; b++) { out.i[b] = f[3 * b]; out.j[b] = f[3 * b + 1]; out.k[b] = f[3 * b + 2]; }
    cache[key] = out;
    return out;
  }
  function axis(title) {
    return {title: {text: title}, showbackground: false, gridcolor: "#e4e4e4", zeroline: false};
  }
  function outside(g) {
    var u = g.units;
    return {aspectmode: "data", xaxis: axis("x (" + u + ")"), yaxis: axis("y (" + u + ")"),
            zaxis: axis("z (" + u + ")"), camera: {eye: {x: 1.2, y: 1.2, z: 0.75}, center: {x: 0, y: 0, z: 0},
            up: {x: 0, y: 0, z: 1}}};
  }
  // From the inside, as the cystoscope sees the wall: axes made a cube about the model's
  // centre (so the scene's (0, 0, 0) is the centre and directions keep their angles), the
  // camera there, looking towards the dome (away from the neck) with anterior up; dragging
  // turns it about a point just ahead, i.e. looks around from the centre.
  function inside(g) {
    var c = g.centre, lo = [g.x, g.y, g.z].map(function (a) { return a.reduce(function (m, v) { return Math.min(m, v); }, Infinity); });
    var hi = [g.x, g.y, g.z].map(function (a) { return a.reduce(function (m, v) { return Math.max(m, v); }, -Infinity); });
    var h = 0;
    for (var d = 0; d < 3; d++) h = Math.max(h, c[d] - lo[d], hi[d] - c[d]);
    var look = g.neck ? [-g.neck[0], -g.neck[1], -g.neck[2]] : [1, 0, 0];
    var up = g.anterior || [0, 0, 1], eps = 0.01, hidden = {visible: false, range: null};
    var scene = {aspectmode: "cube", camera: {eye: {x: 0, y: 0, z: 0},
      center: {x: eps * look[0], y: eps * look[1], z: eps * look[2]}, up: {x: up[0], y: up[1], z: up[2]},
      projection: {type: "perspective"}}};
    ["xaxis", "yaxis", "zaxis"].forEach(function (name, d) {
      scene[name] = Object.assign({}, hidden, {range: [c[d] - h, c[d] + h], autorange: false});
    });
    return scene;
  }
  // The standard regions' borders and names (cystomap.atlas.regions.region_grid), moved off
  // the wall about the centre towards the camera's side (out from outside, in from inside)
  // so the mesh does not hide them.
  var LIFT = {outside: 1.012, inside: 0.985};
  function regionTraces(g, side) {
    var r = g.regions, c = g.centre, f = LIFT[side];
    var lx = [], ly = [], lz = [];
    function at(p, d) { return c[d] + (p[d] - c[d]) * f; }
    r.lines.forEach(function (line) {
      line.forEach(function (p) { lx.push(at(p, 0)); ly.push(at(p, 1)); lz.push(at(p, 2)); });
      lx.push(null); ly.push(null); lz.push(null);
    });
    return [{type: "scatter3d", mode: "lines", x: lx, y: ly, z: lz, hoverinfo: "skip", name: "region borders",
             line: {color: "#ffd21f", width: 4}, meta: "regions"},
            {type: "scatter3d", mode: "text", name: "region names", meta: "regions",
             x: r.labels.map(function (l) { return at(l.xyz, 0); }), y: r.labels.map(function (l) { return at(l.xyz, 1); }),
             z: r.labels.map(function (l) { return at(l.xyz, 2); }), text: r.labels.map(function (l) { return l.text.toUpperCase(); }),
             hoverinfo: "skip", textfont: {color: "#1a1a1a", size: 12}}];
  }
  function withRegions(el, g, side) {
    var shown = el.getAttribute("data-regions") !== "hidden";
    var data = el.data.filter(function (t) { return t.meta !== "regions"; });
    if (g.regions) {
      regionTraces(g, side).forEach(function (t) { t.visible = shown; data.push(t); });
    }
    return data;
  }
  function toggleRegions(button) {
    var el = document.querySelector(".cm-3d[data-view='" + button.getAttribute("data-for") + "']");
    if (!el || el.getAttribute("data-state") !== "drawn") return;
    var show = el.getAttribute("data-regions") === "hidden";
    var idx = [];
    el.data.forEach(function (t, i) { if (t.meta === "regions") idx.push(i); });
    Plotly.restyle(el, {visible: show}, idx).then(function () {
      el.setAttribute("data-regions", show ? "shown" : "hidden");
      button.textContent = show ? "Hide regions" : "Show regions";
    });
  }
  function toggle(button) {
    var el = document.querySelector(".cm-3d[data-view='" + button.getAttribute("data-for") + "']");
    if (!el || el.getAttribute("data-state") !== "drawn") return;
    var g = geometry(data.views[el.getAttribute("data-view")].geometry);
    var goIn = el.getAttribute("data-camera") !== "inside";
    el.setAttribute("data-camera", "moving");
    Plotly.react(el, withRegions(el, g, goIn ? "inside" : "outside"),
                 Object.assign({}, el.layout, {scene: goIn ? inside(g) : outside(g)})).then(function () {
      el.setAttribute("data-camera", goIn ? "inside" : "outside");
      button.textContent = goIn ? "View from outside" : "View from inside";
    });
  }
  document.addEventListener("click", function (e) {
    if (e.target.classList && e.target.classList.contains("cm-inside")) toggle(e.target);
    if (e.target.classList && e.target.classList.contains("cm-regions")) toggleRegions(e.target);
  });
  function draw(el) {
    var view = data.views[el.getAttribute("data-view")];
    var g = geometry(view.geometry), c = bytes(view.colours), n = g.x.length;
    var colours = new Array(n);
    for (var a = 0; a < n; a++) colours[a] = "rgb(" + c[3 * a] + "," + c[3 * a + 1] + "," + c[3 * a + 2] + ")";
    var traces = [{type: "mesh3d", x: g.x, y: g.y, z: g.z, i: g.i, j: g.j, k: g.k, vertexcolor: colours,
      hoverinfo: "skip", flatshading: false,
      lighting: {ambient: 0.85, diffuse: 0.35, specular: 0.03, roughness: 0.9, fresnel: 0.05}}];
    if (view.markers.length) {
      traces.push({type: "scatter3d", mode: "markers+text",
        x: view.markers.map(function (m) { return m.x; }), y: view.markers.map(function (m) { return m.y; }),
        z: view.markers.map(function (m) { return m.z; }), text: view.markers.map(function (m) { return m.label; }),
        hovertext: view.markers.map(function (m) { return m.hover; }), hoverinfo: "text", textposition: "top center",
        marker: {size: 6, color: "#ff28c8", line: {color: "#ffffff", width: 2}},
        textfont: {color: "#111111", size: 15}});
    }
    if (g.regions) {
      el.setAttribute("data-regions", "shown");
      regionTraces(g, "outside").forEach(function (t) { traces.push(t); });
    }
    var layout = {margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: false, paper_bgcolor: "#ffffff",
                  scene: outside(g)};
    el.setAttribute("data-state", "drawing");
    el.setAttribute("data-camera", "outside");
    el.innerHTML = "";
    return Plotly.newPlot(el, traces, layout, {displaylogo: false, responsive: true}).then(function () {
      return new Promise(function (done) { requestAnimationFrame(function () { requestAnimationFrame(done); }); });
    }).then(function () {
      el.setAttribute("data-state", "drawn");
      var button = document.querySelector(".cm-inside[data-for='" + el.getAttribute("data-view") + "']");
      if (button) { button.hidden = !g.centre; button.textContent = "View from inside"; }
      var regions = document.querySelector(".cm-regions[data-for='" + el.getAttribute("data-view") + "']");
      if (regions) { regions.hidden = !g.regions; regions.textContent = "Hide regions"; }
      live.push(el);
      while (live.length > MAX_LIVE) {
        var old = null;
        for (var q = 0; q < live.length; q++) { if (!live[q].cmVisible) { old = live[q]; break; } }
        if (!old) break;
        live.splice(live.indexOf(old), 1);
        Plotly.purge(old);
        old.setAttribute("data-state", "idle");
        var stale = document.querySelector(".cm-inside[data-for='" + old.getAttribute("data-view") + "']");
        if (stale) stale.hidden = true;
        var staleRegions = document.querySelector(".cm-regions[data-for='" + old.getAttribute("data-view") + "']");
        if (staleRegions) staleRegions.hidden = true;
        old.innerHTML = "<p class='placeholder'>3-D view: loads when scrolled into view.</p>";
      }
    });
  }
  function show(el) {
    var state = el.getAttribute("data-state");
    if (state === "drawing" || state === "drawn") return;
    draw(el).catch(function (err) {
      el.setAttribute("data-state", "failed");
      el.textContent = "The 3-D view could not be drawn: " + err;
      console.error("cystomap 3-D view:", err);
    });
  }
  var els = Array.prototype.slice.call(document.querySelectorAll(".cm-3d"));
  if (typeof Plotly === "undefined") {
    els.forEach(function (el) { el.setAttribute("data-state", "failed"); el.textContent = "3-D viewer missing."; });
    throw new Error("cystomap report: plotly.js is missing");
  }
  if (!("IntersectionObserver" in window)) { els.forEach(show); return; }
  var io = new IntersectionObserver(function (entries) {
    entries.forEach(function (e) {
      e.target.cmVisible = e.isIntersecting;
      if (e.isIntersecting) show(e.target);
    });
  }, {rootMargin: "300px 0px"});
  els.forEach(function (el) { el.setAttribute("data-state", "idle"); io.observe(el); });
})();
