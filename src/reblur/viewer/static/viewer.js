/* reblur viewer: the observation's tile pyramid in OpenSeadragon, with the reblurred
 * reference (swipe), change and unknown masks, change outlines by polarity and the
 * estimation windows.  Everything comes from this folder (data.js, tiles/, static/).
 * The page's state goes into document.title for tests:
 *   "regions:N tiles:M failed:K layers:L loaded:0|1"
 * and the image's place on the page into document.body.dataset.imageRect ("left,top,width,
 * height", CSS pixels).
 * Options in the URL hash: #swipe=50 (percent), changes=1 (fill on), region=3 (select and zoom
 * to it), click=X,Y (a click at image pixel X, Y). */
(function () {
  "use strict";
  const D = window.REBLUR_VIEWER;
  const SVG = "http://www.w3.org/2000/svg";
  const DZI = "http://schemas.microsoft.com/deepzoom/2008";
  const items = {};
  const state = { tiles: 0, failed: 0, selected: null };
  const hash = new URLSearchParams(window.location.hash.slice(1));
  const $ = (id) => document.getElementById(id);

  function status() {
    const names = Object.keys(items);
    const loaded = names.length === D.layers.length &&
      names.every((n) => items[n].getOpacity() === 0 || items[n].getFullyLoaded());
    const regions = document.querySelectorAll("#reblur-regions path.region").length;
    document.title = "regions:" + regions + " tiles:" + state.tiles + " failed:" +
      state.failed + " layers:" + names.length + " loaded:" + (loaded ? 1 : 0);
  }

  function source(layer) {
    return { Image: { xmlns: DZI, Url: layer.url, Format: layer.format, Overlap: "0",
      TileSize: String(D.tile_size),
      Size: { Width: String(D.width), Height: String(D.height) } } };
  }

  const viewer = OpenSeadragon({
    id: "osd", prefixUrl: "static/images/", drawer: "canvas",
    imageSmoothingEnabled: false, maxZoomPixelRatio: 64, visibilityRatio: 0.5,
    showNavigator: true, navigatorPosition: "BOTTOM_RIGHT",
    gestureSettingsMouse: { clickToZoom: false },
    tileSources: source(D.layers[0]),
  });
  viewer.addHandler("tile-loaded", () => { state.tiles += 1; status(); });
  viewer.addHandler("tile-load-failed", () => { state.failed += 1; status(); });
  viewer.addHandler("open-failed", () => { state.failed += 1; status(); });
  // until the user moves, a change of the page's layout shows the whole image again
  let moved = false;
  viewer.addHandler("canvas-drag", () => { moved = true; });
  viewer.addHandler("canvas-scroll", () => { moved = true; });
  viewer.addHandler("resize", () => { if (!moved) viewer.viewport.goHome(true); });

  // ------------------------------------------------------------------ overlay (SVG)
  const svg = document.createElementNS(SVG, "svg");
  svg.setAttribute("class", "reblur-overlay");
  const root = document.createElementNS(SVG, "g");
  const gWindows = document.createElementNS(SVG, "g");
  const gRegions = document.createElementNS(SVG, "g");
  const swipeLine = document.createElementNS(SVG, "line");
  gRegions.id = "reblur-regions";
  gWindows.id = "reblur-windows";
  swipeLine.setAttribute("class", "swipe");
  root.append(gWindows, gRegions, swipeLine);
  svg.append(root);

  function el(name, attrs) {
    const e = document.createElementNS(SVG, name);
    for (const k in attrs) e.setAttribute(k, attrs[k]);
    return e;
  }

  function polarityClass(r) {
    return ["brighter", "darker", "mixed"].includes(r.polarity) ? r.polarity : "other";
  }

  const paths = {};
  for (const r of D.regions) {
    if (!r.outline.length) continue;
    const d = r.outline.map((ring) => "M" + ring.map((p) => p[0] + "," + p[1]).join("L") + "Z")
      .join("");
    paths[r.id] = el("path", { d: d, class: "region " + polarityClass(r), "data-id": r.id });
    gRegions.append(paths[r.id]);
  }
  for (const [y0, x0, h, w] of D.windows) {
    gWindows.append(el("rect", { x: x0, y: y0, width: w, height: h, class: "window" }));
  }

  function scaleOf() {
    const it = items.observed;
    const p0 = it.imageToViewerElementCoordinates(new OpenSeadragon.Point(0, 0));
    const p1 = it.imageToViewerElementCoordinates(new OpenSeadragon.Point(1, 0));
    return { p0: p0, s: p1.x - p0.x };
  }

  function place() {
    if (!items.observed) return;
    const t = scaleOf();
    root.setAttribute("transform", "matrix(" + t.s + ",0,0," + t.s + "," + t.p0.x + "," +
      t.p0.y + ")");
    const box = viewer.element.getBoundingClientRect();
    document.body.dataset.imageRect = [box.left + t.p0.x, box.top + t.p0.y, t.s * D.width,
      t.s * D.height].map((v) => v.toFixed(1)).join(",");
  }

  // ------------------------------------------------------------------ layers
  function applyLayers() {
    const show = (name, on) => { if (items[name]) items[name].setOpacity(on ? 1 : 0); };
    show("changes", $("show-changes").checked);
    show("unknown", $("show-unknown").checked);
    gRegions.style.display = $("show-outlines").checked ? "" : "none";
    gWindows.style.display = $("show-windows").checked ? "" : "none";
    const v = Number($("swipe").value) / 100;
    const x = v * D.width;
    if (items.reblurred) {
      items.reblurred.setOpacity(v > 0 ? 1 : 0);
      if (v > 0) items.reblurred.setClip(new OpenSeadragon.Rect(0, 0, x, D.height));
    }
    swipeLine.style.display = v > 0 && v < 1 && items.reblurred ? "" : "none";
    for (const [k, val] of [["x1", x], ["x2", x], ["y1", 0], ["y2", D.height]]) {
      swipeLine.setAttribute(k, val);
    }
    status();
  }
  for (const id of ["show-outlines", "show-changes", "show-unknown", "show-windows", "swipe"]) {
    $(id).addEventListener("input", applyLayers);
  }
  if (!D.layers.some((l) => l.name === "reblurred")) {
    $("swipe").disabled = true;
    $("swipe-label").title = "no reblurred reference in this result";
  }
  if (hash.has("swipe")) $("swipe").value = hash.get("swipe");
  if (hash.has("changes")) $("show-changes").checked = hash.get("changes") === "1";

  function addLayers(k) {
    if (k >= D.layers.length) { applyLayers(); return; }
    const layer = D.layers[k];
    viewer.addTiledImage({
      tileSource: source(layer), index: k, opacity: 0,
      success: (e) => {
        items[layer.name] = e.item;
        e.item.addHandler("fully-loaded-change", status);
        addLayers(k + 1);
      },
      error: () => { state.failed += 1; status(); addLayers(k + 1); },
    });
  }

  viewer.addOnceHandler("open", () => {
    items.observed = viewer.world.getItemAt(0);
    items.observed.addHandler("fully-loaded-change", status);
    viewer.canvas.append(svg);
    viewer.addHandler("update-viewport", place);
    place();
    addLayers(1);
    if (hash.has("region")) select(Number(hash.get("region")), true);
    if (/^[\d.]+,[\d.]+$/.test(hash.get("click") || "")) {
      const [x, y] = hash.get("click").split(",").map(Number);
      select(pick(x, y, 6 / scaleOf().s), false);
    }
    status();
  });

  // ------------------------------------------------------------------ regions: click, list
  const fmt = (v) => (typeof v === "number" && !Number.isInteger(v) ? v.toPrecision(4) : v);
  const LABELS = [["id", "id"], ["rank", "rank"], ["score", "score (x threshold)"],
    ["polarity", "polarity"], ["area", "area (px)"], ["area_m2", "area (CRS units\u00b2)"],
    ["mean_contrast", "mean contrast"], ["mean_stat", "mean statistic"],
    ["max_stat", "max statistic"], ["bbox", "bbox (y0, x0, y1, x1)"],
    ["centroid", "centroid (row, col)"], ["exact", "outline exact"]];

  function select(id, zoom) {
    const r = D.regions.find((q) => q.id === id);
    if (state.selected !== null && paths[state.selected]) {
      paths[state.selected].classList.remove("selected");
    }
    document.querySelectorAll("#list tr.selected").forEach((tr) => tr.classList.remove("selected"));
    state.selected = r ? r.id : null;
    if (!r) { $("details").innerHTML = "<p>No region there.</p>"; return; }
    if (paths[r.id]) paths[r.id].classList.add("selected");
    const row = document.querySelector('#list tr[data-id="' + r.id + '"]');
    if (row) row.classList.add("selected");
    const t = document.createElement("table");
    for (const [k, label] of LABELS) {
      if (r[k] === undefined || r[k] === null) continue;
      const v = Array.isArray(r[k]) ? r[k].map((x) => fmt(x)).join(", ") : fmt(r[k]);
      const tr = t.insertRow();
      tr.insertCell().outerHTML = "<th>" + label + "</th>";
      tr.insertCell().textContent = String(v);
    }
    $("details").replaceChildren(t);
    if (zoom && r.bbox && items.observed) {
      const [y0, x0, y1, x1] = r.bbox;
      const pad = Math.max(8, 0.5 * Math.max(y1 - y0, x1 - x0));
      viewer.viewport.fitBounds(items.observed.imageToViewportRectangle(
        x0 - pad, y0 - pad, x1 - x0 + 2 * pad, y1 - y0 + 2 * pad));
    }
  }

  function inside(rings, x, y) {
    let c = false;
    for (const ring of rings) {
      for (let i = 0, j = ring.length - 1; i < ring.length; j = i++) {
        const [xi, yi] = ring[i];
        const [xj, yj] = ring[j];
        if ((yi > y) !== (yj > y) && x < ((xj - xi) * (y - yi)) / (yj - yi) + xi) c = !c;
      }
    }
    return c;
  }

  function edgeDistance(rings, x, y) {
    let d = Infinity;
    for (const ring of rings) {
      for (let i = 0, j = ring.length - 1; i < ring.length; j = i++) {
        const [xi, yi] = ring[i];
        const [xj, yj] = ring[j];
        const ex = xj - xi, ey = yj - yi;
        const len2 = ex * ex + ey * ey;
        const t = len2 > 0 ? Math.min(1, Math.max(0, ((x - xi) * ex + (y - yi) * ey) / len2)) : 0;
        d = Math.min(d, Math.hypot(x - xi - t * ex, y - yi - t * ey));
      }
    }
    return d;
  }

  // the region whose outline holds the point (even-odd rule: not in its holes), else the
  // one whose outline passes within tol image pixels
  function pick(x, y, tol) {
    let best = null;
    for (const r of D.regions) {
      if (!r.bbox || !r.outline) continue;
      const [y0, x0, y1, x1] = r.bbox;
      if (Math.max(x0 - x, 0, x - x1) > tol || Math.max(y0 - y, 0, y - y1) > tol) continue;
      const d = inside(r.outline, x, y) ? -1 : edgeDistance(r.outline, x, y);
      if (d <= tol && (best === null || d < best.d)) best = { d: d, id: r.id };
    }
    return best ? best.id : null;
  }

  viewer.addHandler("canvas-click", (e) => {
    if (!e.quick || !items.observed || !$("show-outlines").checked) return;
    const p = items.observed.viewerElementToImageCoordinates(e.position);
    select(pick(p.x, p.y, 6 / scaleOf().s), false);
  });

  const list = $("list");
  list.innerHTML = "<tr><th>#</th><th>score</th><th>polarity</th><th>area</th></tr>";
  for (const r of D.regions.slice(0, 100)) {
    const tr = list.insertRow();
    tr.className = "row";
    tr.dataset.id = r.id;
    for (const v of [r.id, fmt(r.score), r.polarity || "-", r.area]) {
      tr.insertCell().textContent = v === undefined ? "-" : String(v);
    }
    tr.addEventListener("click", () => select(r.id, true));
  }
  $("summary").textContent = D.width + " x " + D.height + " px; " + D.n_regions +
    " change region" + (D.n_regions === 1 ? "" : "s") +
    (D.shown < D.n_regions ? ", outlines of the " + D.shown + " strongest" : "") + "; " +
    D.windows.length + " estimation window" + (D.windows.length === 1 ? "" : "s") + ".";
  for (const n of D.notes) {
    const li = document.createElement("li");
    li.textContent = n;
    $("notes").append(li);
  }
  status();
})();
