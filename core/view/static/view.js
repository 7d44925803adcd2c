// The operator view: polls /api/state, pulls live frames one at a time (never faster than the
// browser shows them), and reads parts from the results store. No framework, no external assets.
"use strict";

const $ = (id) => document.getElementById(id);
const view = { mode: null, run: null, selectedRun: null, seq: 0, maxFps: 10, filmIds: "", page: 1, perPage: 25,
               partsKey: "", lastPartsLoad: 0, metaLoaded: false, lastMeta: 0, reviewImagePart: null };

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v; else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
    else node.setAttribute(k, v);
  }
  for (const c of children) node.append(c instanceof Node ? c : document.createTextNode(c ?? ""));
  return node;
}

const fmt = (v, digits = 2, signed = false) =>
  v === null || v === undefined ? "n/a" : (signed && v > 0 ? "+" : "") + Number(v).toFixed(digits);
// a measurement with its standard uncertainty u, as the store keeps it
const withSigma = (v, u, digits, signed = false) =>
  fmt(v, digits, signed) + (v === null || v === undefined || u === null || u === undefined ? "" : ` ± ${Number(u).toFixed(digits)}`);
const clock = (t) => new Date(t * 1000).toLocaleTimeString();

async function getJSON(url) {
  const r = await fetch(url, { cache: "no-store" });
  if (!r.ok) {
    // the inspection PC answered with its reason (a results store it cannot read): that, not "no connection"
    let said = "";
    try { said = (await r.json()).error || ""; } catch (e) { /* not an answer of ours */ }
    const error = new Error(said || `${url}: ${r.status}`);
    error.answered = Boolean(said);
    throw error;
  }
  return r.json();
}

function runParam(prefix = "?") {
  return view.mode === "review" && view.selectedRun ? `${prefix}run=${view.selectedRun}` : "";
}

// -- state ------------------------------------------------------------------------------------
async function pollState() {
  try {
    const s = await getJSON("/api/state" + runParam());
    $("connection").textContent = "connected";
    $("connection").className = "tag ok";
    render(s);
  } catch (e) {
    $("connection").textContent = e.answered ? e.message : "no connection to the inspection PC";
    $("connection").className = "tag bad";
  }
  setTimeout(pollState, 500);
}

function render(s) {
  const first = view.mode === null;
  view.mode = s.mode;
  view.run = s.run_id;
  view.maxFps = s.max_fps || 10;
  document.body.dataset.mode = s.mode;
  $("recipe").textContent = s.recipe || "";
  $("mode").textContent = s.mode === "live" ? "LIVE" : "REVIEW";
  $("run-state").textContent = s.run_id ? `run ${s.run_id} · ${s.state}` : s.state;
  // the master parts checked before the first plate (verify.path): the tally, or why the line did not start
  const m = s.master_parts;
  $("masters").textContent = m ? (m.started ? "master parts ✓" : "master parts failed") : "no master parts";
  $("masters").className = "tag" + (m ? (m.started ? " ok" : " bad") : "");
  $("masters").title = m ? m.text : "the recipe names no master parts (verify.path)";
  if (first) {
    if (s.mode === "live") pullFrames(); else $("frame-note").textContent = "review of a finished run: click a part to see it";
  }
  if (!view.metaLoaded || (s.mode === "live" && Date.now() - view.lastMeta > 5000)) loadMeta();

  const v = s.verdict;
  const box = $("verdict");
  box.className = "verdict " + (v ? v.status : "none");
  $("verdict-status").textContent = v ? v.status : "—";
  $("verdict-part").textContent = v ? `${v.part_id} · frame ${v.frame_id}` : "waiting for the first part";
  $("verdict-reasons").textContent = v && v.status !== "PASS" ? v.reasons.join(" | ") : "";
  $("verdict-reasons").title = $("verdict-reasons").textContent;
  if (s.mode === "review" && v && view.reviewImagePart === null) showReviewImage(s.filmstrip[0]?.part_id);

  const c = s.counters;
  $("count-parts").textContent = c.parts;
  $("count-passed").textContent = c.passed;
  $("count-rejected").textContent = c.rejected;
  $("count-errors").textContent = c.errors;
  $("count-flagged").textContent = c.flagged;
  $("count-yield").textContent = c.yield_percent === null ? "–" : `${c.yield_percent.toFixed(1)} %`;
  $("count-fps").textContent = s.fps === null ? "–" : s.fps.toFixed(1);
  const perClass = $("per-class");
  perClass.replaceChildren(...Object.entries(c.rejects_per_class).map(([cls, n]) =>
    el("li", {}, el("span", {}, cls), el("b", {}, String(n)))));
  if (!perClass.children.length) perClass.append(el("li", { class: "muted" }, "none"));

  renderAlarms(s.alarms);
  renderFilmstrip(s.filmstrip);
  maybeReloadParts(c.parts);
}

function renderAlarms(alarms) {
  const list = $("alarms");
  if (!alarms.length) { list.replaceChildren(el("li", { class: "muted" }, "none")); return; }
  list.replaceChildren(...alarms.map((a) => el("li", { class: "alarm", "data-alarm": a.id },
    el("span", {}, `${clock(a.time)} ${a.source}: ${a.message}`),
    el("button", { class: "ack", onclick: () => acknowledge(a.id) }, "acknowledge"))));
}

async function acknowledge(id) {
  await fetch(`/api/alarms/${id}/ack`, { method: "POST" });
  pollStateOnce();
}

async function pollStateOnce() {
  try { render(await getJSON("/api/state" + runParam())); } catch (e) { /* the next poll reports it */ }
}

function renderFilmstrip(items) {
  const ids = items.map((p) => p.part_id).join(",");
  if (ids === view.filmIds) return;  // unchanged: keep the thumbnails (and the operator's click target)
  view.filmIds = ids;
  const strip = $("filmstrip");
  if (!items.length) { strip.replaceChildren(el("span", { class: "muted" }, "none yet")); return; }
  strip.replaceChildren(...items.map((p) => el("button", { class: `film-item ${p.verdict}`, "data-part": p.part_id,
      onclick: () => openDetail(p.part_id) },
    el("img", { src: `/api/parts/${encodeURIComponent(p.part_id)}/image.jpg?w=160`, alt: p.part_id, loading: "lazy" }),
    el("b", {}, `${p.verdict} ${p.part_id}`),
    el("small", {}, p.classes.join(", ") || p.reasons.join(" | ")),
    el("small", {}, clock(p.time)))));
}

// -- live frames: one request at a time, paced to max_fps --------------------------------------
async function pullFrames() {
  for (;;) {
    const started = performance.now();
    try {
      const r = await fetch(`/api/frame.jpg?after=${view.seq}`, { cache: "no-store" });
      if (r.status === 200) {
        const seq = Number(r.headers.get("X-Frame-Seq"));
        const url = URL.createObjectURL(await r.blob());
        const img = $("frame");
        const old = img.dataset.url;
        img.src = url;
        img.dataset.url = url;
        img.dataset.seq = String(seq);
        if (old) URL.revokeObjectURL(old);
        if (seq === view.seq) await sleep(1000);  // the line stands still (run finished)
        view.seq = seq;
      } else {
        await sleep(500);
      }
    } catch (e) {
      await sleep(1000);
    }
    const wait = 1000 / view.maxFps - (performance.now() - started);
    if (wait > 0) await sleep(wait);
  }
}

function showReviewImage(partId) {
  if (!partId) return;
  view.reviewImagePart = partId;
  $("frame").src = `/api/parts/${encodeURIComponent(partId)}/image.jpg`;
}

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

// -- parts table (review, filters, pages, CSV) --------------------------------------------------
async function loadMeta() {
  view.lastMeta = Date.now();
  try {
    const meta = await getJSON("/api/meta");
    view.metaLoaded = true;
    const classSel = $("filter-class");
    const chosen = classSel.value;
    classSel.replaceChildren(el("option", { value: "" }, "all"), ...meta.classes.map((c) => el("option", {}, c)));
    classSel.value = meta.classes.includes(chosen) ? chosen : "";
    const runSel = $("run-select");
    const run = view.selectedRun ?? view.run;
    runSel.replaceChildren(...meta.runs.map((r) => el("option", { value: r.id }, `${r.id} · ${r.recipe_name} · ${r.parts ?? "…"} parts`)));
    if (run) runSel.value = String(run);
    runSel.disabled = view.mode === "live";
  } catch (e) { /* retried on the next state poll */ }
}

function partsQuery() {
  const q = new URLSearchParams();
  const run = view.mode === "review" ? view.selectedRun : view.run;
  if (run) q.set("run", run);
  if ($("filter-verdict").value) q.set("verdict", $("filter-verdict").value);
  if ($("filter-class").value) q.set("class", $("filter-class").value);
  return q;
}

function maybeReloadParts(total) {
  const key = `${partsQuery()}|${view.page}|${total}`;
  // live lines produce parts continuously: refresh the first page at most once a second
  if (key === view.partsKey || (view.page > 1 && view.mode === "live") || Date.now() - view.lastPartsLoad < 1000) return;
  loadParts();
}

async function loadParts() {
  const q = partsQuery();
  $("export-csv").href = `/api/export.csv?${q}`;
  q.set("page", view.page);
  q.set("per_page", view.perPage);
  view.lastPartsLoad = Date.now();
  try {
    const data = await getJSON(`/api/parts?${q}`);
    view.partsKey = `${partsQuery()}|${view.page}|${$("count-parts").textContent}`;
    const pages = Math.max(1, Math.ceil(data.total / data.per_page));
    $("page-info").textContent = `page ${data.page} of ${pages} · ${data.total} parts`;
    $("page-prev").disabled = data.page <= 1;
    $("page-next").disabled = data.page >= pages;
    $("parts-table").tBodies[0].replaceChildren(...data.parts.map((p) => el("tr", { "data-part": p.part_id,
        onclick: () => openDetail(p.part_id) },
      el("td", {}, p.part_id), el("td", {}, p.frame_id), el("td", {}, clock(p.time)),
      el("td", { class: p.verdict }, p.verdict), el("td", {}, p.classes.join(", ")),
      el("td", { class: "reason", title: p.reasons.join("\n") }, p.verdict === "PASS" ? "" : p.reasons.join(" | ")))));
  } catch (e) { /* the connection tag says so */ }
}

function resetParts() { view.page = 1; view.partsKey = ""; loadParts(); }

// -- detail dialog ------------------------------------------------------------------------------
// what a deviation's uncertainty is made of, largest first, each part as its share of the variance
function uncertaintyParts(parts) {
  const total = parts.reduce((sum, p) => sum + p.variance_mm2, 0);
  if (!(total > 0)) return "";
  return "uncertainty:\n" + [...parts].sort((a, b) => b.variance_mm2 - a.variance_mm2)
    .map((p) => `${Math.round(100 * p.variance_mm2 / total)} % ${p.cause}`).join("\n");
}

async function openDetail(partId) {
  const p = await getJSON(`/api/parts/${encodeURIComponent(partId)}`);
  $("detail-title").textContent = `${p.part_id} · frame ${p.frame_id} · ${clock(p.time)}`;
  const verdict = $("detail-verdict");
  verdict.textContent = p.verdict;
  verdict.className = `verdict-inline ${p.verdict}`;
  $("detail-rule").textContent = p.verdict === "PASS" ? "no rule rejected this part" : `rejected by: ${p.reasons.join(" | ")}`;
  const img = $("detail-image");
  img.hidden = false;
  img.onerror = () => { img.hidden = true; };
  img.src = p.image_url;
  $("detail-defects").tBodies[0].replaceChildren(...p.defects.map((d) => el("tr", {},
    el("td", {}, d.class), el("td", {}, fmt(d.confidence)), el("td", {}, withSigma(d.distance_mm, d.distance_sigma_mm, 1)),
    el("td", { title: uncertaintyParts(d.uncertainty) }, withSigma(d.deviation_mm, d.deviation_sigma_mm, 2, true)),
    el("td", {}, `${Math.round(100 * d.valid_fraction)} %`),
    el("td", { class: d.verdict }, d.verdict), el("td", {}, [...d.reasons, d.note].filter(Boolean).join(" | ")))));
  $("detail-events").replaceChildren(...p.output_events.map((e) =>
    el("div", { class: "muted" }, `${clock(e.time)} ${e.output}: ${e.command} → ${e.outcome} ${e.detail || ""}`)));
  if (view.mode === "review") showReviewImage(partId);
  const dialog = $("detail");
  if (!dialog.open) dialog.showModal();
}

$("filter-verdict").addEventListener("change", resetParts);
$("filter-class").addEventListener("change", resetParts);
$("page-prev").addEventListener("click", () => { view.page = Math.max(1, view.page - 1); loadParts(); });
$("page-next").addEventListener("click", () => { view.page += 1; loadParts(); });
$("run-select").addEventListener("change", (e) => {
  view.selectedRun = Number(e.target.value);
  view.filmIds = "";
  view.reviewImagePart = null;
  resetParts();
  pollStateOnce();
});

pollState();
