// The bonemesh page: the API key (this tab's sessionStorage, or the device's localStorage when asked; never in a
// URL), upload with progress, job polling, cancel, the 3D view (<model-viewer>, decoders served by this server),
// downloads, QR code and the key's recent jobs. Every value from the API is put on the page as text (textContent,
// attributes), never as HTML; the page runs under a Content-Security-Policy without inline script.
"use strict";
// model-viewer reads this before it defines itself (this script runs first: see index.html): every decoder comes
// from this server, none from a CDN
self.ModelViewerElement = Object.assign(self.ModelViewerElement || {}, {
  dracoDecoderLocation: "/vendor/draco/",
  ktx2TranscoderLocation: "/vendor/basis/",
  meshoptDecoderLocation: "/vendor/meshopt_decoder.js",
  lottieLoaderLocation: "/vendor/lottie-not-used.js",
});
const $ = (id) => document.getElementById(id);
const KEY = "bonemesh-api-key";
// the files are the job's outputs as the API lists them: each with its kind and purpose from the server's registry
// (engine/export/files.py); the page knows kinds only, never file names
let picked = null; // {name, blob}
let polling = null;
let current = null;
let following = 0; // which call of follow() the running poll belongs to

// the key: in this tab (sessionStorage: gone when the tab closes, never shared with other tabs, never sent but in
// the X-API-Key header), or on this device (localStorage) only when "remember it on this device" is ticked
function key() { return sessionStorage.getItem(KEY) || localStorage.getItem(KEY) || ""; }
function setKey(value, remember) {
  sessionStorage.removeItem(KEY); localStorage.removeItem(KEY);
  if (value) (remember ? localStorage : sessionStorage).setItem(KEY, value);
  showKeyState();
}
function showKeyState() {
  const remembered = !!localStorage.getItem(KEY), set = !!key();
  $("key-remember").checked = remembered;
  $("key-forget").hidden = !set;
  $("key-state").textContent = !set ? "kept in this browser tab only, until the tab is closed; never in a link"
    : remembered ? "key remembered on this device (Forget the key removes it)"
      : "key set for this tab: forgotten when the tab is closed";
}
function headers() { return { "X-API-Key": key() }; }
function human(bytes) {
  const u = ["B", "kB", "MB", "GB"]; let i = 0;
  while (bytes >= 1000 && i < u.length - 1) { bytes /= 1000; i++; }
  return `${bytes.toFixed(i ? 1 : 0)} ${u[i]}`;
}
async function api(path, options = {}) {
  const resp = await fetch(path, { ...options, headers: { ...headers(), ...(options.headers || {}) } });
  const body = resp.status === 204 ? null : await resp.json().catch(() => null);
  if (!resp.ok) {
    throw Object.assign(new Error((body && body.detail) || `${resp.status} ${resp.statusText}`), { status: resp.status, body });
  }
  return body;
}

// --- a zip (stored, no compression) of several files: a folder of slices or a DICOM series -------------------
const CRC = (() => { const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) { let c = n; for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1; t[n] = c >>> 0; }
  return t; })();
function crc32(bytes) { let c = 0xffffffff; for (let i = 0; i < bytes.length; i++) c = CRC[(c ^ bytes[i]) & 0xff] ^ (c >>> 8); return (c ^ 0xffffffff) >>> 0; }
async function zipFiles(files) {
  const parts = [], central = []; let offset = 0;
  for (const f of files) {
    const data = new Uint8Array(await f.arrayBuffer());
    const name = new TextEncoder().encode((f.webkitRelativePath || f.name).replace(/^\/+/, ""));
    const crc = crc32(data);
    const local = new DataView(new ArrayBuffer(30));
    local.setUint32(0, 0x04034b50, true); local.setUint16(4, 20, true); local.setUint16(6, 0x800, true);
    local.setUint32(14, crc, true); local.setUint32(18, data.length, true); local.setUint32(22, data.length, true);
    local.setUint16(26, name.length, true);
    const entry = new DataView(new ArrayBuffer(46));
    entry.setUint32(0, 0x02014b50, true); entry.setUint16(4, 20, true); entry.setUint16(6, 20, true);
    entry.setUint16(8, 0x800, true); entry.setUint32(16, crc, true); entry.setUint32(20, data.length, true);
    entry.setUint32(24, data.length, true); entry.setUint16(28, name.length, true); entry.setUint32(42, offset, true);
    parts.push(local, name, data); central.push(entry, name);
    offset += 30 + name.length + data.length;
  }
  const size = central.reduce((s, p) => s + p.byteLength, 0);
  const end = new DataView(new ArrayBuffer(22));
  end.setUint32(0, 0x06054b50, true); end.setUint16(8, files.length, true); end.setUint16(10, files.length, true);
  end.setUint32(12, size, true); end.setUint32(16, offset, true);
  return new Blob([...parts, ...central, end], { type: "application/zip" });
}
async function entriesOf(entry, prefix = "") { // files of a dropped folder
  if (entry.isFile) return [await new Promise((ok, no) => entry.file((f) => ok(
    Object.defineProperty(f, "webkitRelativePath", { value: prefix + f.name })), no))];
  const reader = entry.createReader(); const out = [];
  for (;;) {
    const batch = await new Promise((ok, no) => reader.readEntries(ok, no));
    if (!batch.length) break;
    for (const e of batch) out.push(...await entriesOf(e, `${prefix}${entry.name}/`));
  }
  return out;
}
// files that are never slices nor DICOM: refused here under their own names (a zip of them would be "slices.zip")
const NOT_A_SCAN = /\.(txt|md|csv|json|xml|html?|pdf|docx?|xlsx?|rtf|log)$/i;
function pickedText(text, error = false) {
  $("picked").textContent = text;
  $("picked").className = error ? "error" : "muted";
  $("picked").dataset.state = error ? "refused" : "";
}
async function pick(files) {
  resetUpload();
  const hidden = files.filter((f) => f.name.startsWith("."));
  files = files.filter((f) => !f.name.startsWith("."));
  if (!files.length) {
    picked = null;
    pickedText(hidden.length ? `${hidden.map((f) => f.name).join(", ")}: hidden files only; choose a zip, a folder `
      + "of slices or the files of a DICOM series" : "nothing to upload in what was dropped (an empty folder?)", true);
    return;
  }
  const odd = files.filter((f) => NOT_A_SCAN.test(f.name));
  if (odd.length === files.length) {
    picked = null;
    pickedText(`${odd.map((f) => f.name).join(", ")}: not slice images or DICOM files; choose a zip, `
      + "a folder of slices or the files of a DICOM series", true);
    return;
  }
  files = files.filter((f) => !NOT_A_SCAN.test(f.name)); // a folder's notes or readme are left out
  // one file goes as it is, under its own name (an archive, a .npy, a TIFF, a DICOM file), so that the service's
  // messages name it; several are packed into one zip named after their folder
  const single = files.length === 1;
  const folder = (files[0].webkitRelativePath || "").split("/")[0] || files[0].name.replace(/\.[^.]*$/, "");
  pickedText(single ? `${files[0].name} (${human(files[0].size)})` : `${files.length} files: packing…`);
  picked = single ? { name: files[0].name, blob: files[0] } : { name: `${folder}.zip`, blob: await zipFiles(files) };
  if (!single) pickedText(`${files.length} files (${human(picked.blob.size)} as a zip)`);
}

// --- upload, then follow the job ----------------------------------------------------------------------------
// the voxel size: empty, or three numbers z, y, x in mm; anything else is refused naming the field
function voxelSize() {
  const text = $("spacing").value.trim();
  if (!text) return null;
  const parts = text.split(/[ ,;xX×]+/).filter(Boolean);
  const values = parts.map(Number);
  if (values.length !== 3 || values.some((v) => !Number.isFinite(v) || v <= 0)) {
    throw Object.assign(new Error(`Voxel size: give three positive numbers z, y, x in mm (e.g. 1.5, 0.957, 0.957); got "${text}"`), { field: "spacing" });
  }
  return values;
}
function orientOf() {
  return { first_slice: $("first-slice").value, flip_lr: $("flip-lr").checked, flip_ap: $("flip-ap").checked };
}
function params() {
  const p = {}; const kind = $("level-kind").value;
  if (kind === "iso") p.iso = Number($("iso").value);
  else if (kind !== "auto") p.preset = kind;
  if ($("hu-offset").value) p.hu_offset = Number($("hu-offset").value);
  const spacing = voxelSize();
  if (spacing) p.spacing = spacing;
  p.orient = orientOf();
  if ($("reduction").value) p.reduction = Number($("reduction").value);
  if ($("defect").checked) p.defect = $("defect-side").value ? { side: $("defect-side").value } : {};
  Object.assign(p, partsParams());
  return p;
}
// pieces (the N largest bone pieces of a CT as parts) and a region of interest (cropped before anything runs):
// "z0:z1, y0:y1, x0:x1" voxel indices, or "x0:x1, y0:y1, z0:z1" mm in the patient frame; refused naming the field
function partsParams() {
  const p = {};
  const pieces = $("pieces").value.trim();
  if (pieces) {
    const n = Number(pieces);
    if (!Number.isInteger(n) || n < 1 || n > 1000) {
      throw Object.assign(new Error(`Pieces: give a whole number from 1 to 1000; got "${pieces}"`), { field: "pieces" });
    }
    p.pieces = n;
  }
  const text = $("roi").value.trim();
  if (text) {
    const box = text.split(",").map((r) => r.split(":").map((v) => Number(v.trim())));
    if (box.length !== 3 || box.some((r) => r.length !== 2 || r.some((v) => !Number.isFinite(v)) || r[0] >= r[1])) {
      throw Object.assign(new Error(`Region: give three ranges lo:hi separated by commas (${ROI_HINTS[$("roi-units").value]}); got "${text}"`), { field: "roi" });
    }
    p.roi = { box, units: $("roi-units").value };
  }
  return p;
}
// the scan goes straight to the store when the API says it can (S3 storage: GET /v1/upload-options), in parts sent
// 4 at a time; otherwise, or when the store cannot be reached from this page (e.g. no CORS rule), through the API
async function upload() {
  resetUpload();
  $("upload-progress").hidden = false;
  if (!key()) { refused("Enter your API key first (at the top of the page).", "api-key"); reveal($("key-box")); return; }
  if (!picked) { refused("Choose a scan first: drop it on the page, or use Choose a zip or files.", "drop"); return; }
  reveal($("upload-progress"));
  let fields;
  try { fields = params(); } catch (e) {
    refused(e.message, e.field); return;
  }
  $("start").disabled = true;
  const options = await api("/v1/upload-options").catch(() => ({ direct: false }));
  if (options.direct) {
    try { uploaded(await directUpload(fields, options.parallel_parts || 4)); return; } catch (e) {
      if (e.status && e.status !== 409) { refused(e.message, null, e.body); return; } // the API's answer: the same through it
      console.warn("direct upload failed, uploading through the API", e);
    }
  }
  formUpload(fields);
}
function uploaded(job) {
  if (picked) picked.keys = {}; // sent: uploading it again is a new job
  $("start").disabled = false;
  $("upload-bar").value = 100; $("upload-text").textContent = "uploaded";
  follow(job.id); loadJobs();
}
function resetUpload() {
  $("upload-bar").value = 0; $("upload-text").textContent = ""; $("upload-progress").dataset.state = "";
  $("spacing").classList.remove("needed");
}
// the scan lacks its voxel size (the API's no_spacing: a refused upload or a failed job): the page's own words,
// pointing at the field, never the API's ("send "spacing" in params")
const NO_SPACING = "The files do not say how large a voxel is: fill in the Voxel size field above (z, y, x in mm, "
  + "e.g. 1.5, 0.5, 0.5), then press Make the model again.";
function isNoSpacing(code, detail) {
  return code === "no_spacing" || /no_spacing/.test(code || "") || /how large a voxel is|"spacing"/.test(detail || "");
}
function askForSpacing() {
  const field = $("spacing");
  field.classList.add("needed"); reveal(field); field.focus({ preventScroll: true });
}
// the upload refused (by the form's check, or by the API: 4xx problem+json): the reason in red, the bar gone
function refused(detail, field = null, body = null) {
  $("start").disabled = false;
  $("upload-bar").value = 0; $("upload-progress").dataset.state = "refused";
  const code = body && (body.code || body.type);
  if (field === null && isNoSpacing(code, String(detail))) {
    $("upload-text").textContent = `refused: ${NO_SPACING}`; askForSpacing();
  } else {
    $("upload-text").textContent = field ? detail : `refused: ${detail}`;
    if (field) { $(field).focus({ preventScroll: true }); if (field === "spacing") $("spacing").classList.add("needed"); }
  }
  reveal($("upload-progress"));
}
function uploading(loaded, total, where) {
  $("upload-bar").value = (100 * loaded) / total;
  $("upload-text").textContent = `uploading ${human(loaded)} of ${human(total)}${where}`;
}
// one Idempotency-Key per file and settings until the upload succeeds: pressing upload again after the network
// dropped the answer gives the job the first press made, not a second one (docs/api.md)
function idempotencyKey(fields) {
  const what = JSON.stringify(fields);
  picked.keys = picked.keys || {};
  if (!picked.keys[what]) {
    const bytes = crypto.getRandomValues(new Uint8Array(16));
    picked.keys[what] = Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
  }
  return picked.keys[what];
}
function formUpload(fields) {
  $("upload-progress").dataset.via = "api";
  const form = new FormData();
  form.append("file", picked.blob, picked.name);
  form.append("params", JSON.stringify(fields));
  const xhr = new XMLHttpRequest();
  xhr.open("POST", "/v1/jobs");
  xhr.setRequestHeader("X-API-Key", key());
  xhr.setRequestHeader("Idempotency-Key", idempotencyKey(fields));
  xhr.upload.onprogress = (e) => { if (e.lengthComputable) uploading(e.loaded, e.total, ""); };
  xhr.onload = () => {
    let body = null; try { body = JSON.parse(xhr.responseText); } catch (e) { /* not JSON */ }
    if (xhr.status !== 202) { refused((body && body.detail) || `the server answered ${xhr.status}`, null, body); return; }
    uploaded(body);
  };
  xhr.onerror = () => refused("the upload failed (the network or the server went away); try again");
  xhr.send(form);
}
// one part: PUT to its presigned link with exactly the headers the API listed; resolves to its ETag (null when the
// store's CORS rule does not expose it: the API then takes the parts the store holds)
function putPart(part, blob, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open(part.method || "PUT", part.url);
    for (const [name, value] of Object.entries(part.headers || {})) xhr.setRequestHeader(name, value);
    xhr.upload.onprogress = (e) => onProgress(e.loaded);
    xhr.onload = () => (xhr.status >= 200 && xhr.status < 300 ? resolve(xhr.getResponseHeader("ETag"))
      : reject(new Error(`the store answered ${xhr.status} to part ${part.number}`)));
    xhr.onerror = () => reject(new Error(`the store could not be reached for part ${part.number}`));
    xhr.send(blob.slice(part.offset, part.offset + part.bytes));
  });
}
async function directUpload(fields, parallel) {
  const json = { "Content-Type": "application/json" };
  const body = { filename: picked.name, size: picked.blob.size, params: fields };
  const up = await api("/v1/uploads", { method: "POST", headers: json, body: JSON.stringify(body) });
  $("upload-progress").dataset.via = "store";
  const sent = up.parts.map(() => 0), etags = up.parts.map(() => null);
  let next = 0;
  const sender = async () => {
    while (next < up.parts.length) {
      const part = up.parts[next++];
      etags[part.number - 1] = await putPart(part, picked.blob, (n) => {
        sent[part.number - 1] = n; uploading(sent.reduce((a, b) => a + b, 0), picked.blob.size, " (straight to the store)");
      });
      sent[part.number - 1] = part.bytes;
    }
  };
  try { await Promise.all(Array.from({ length: Math.min(parallel, up.parts.length) }, sender)); } catch (e) {
    api(up.abort_url, { method: "DELETE" }).catch(() => null); // the store keeps nothing of it
    throw e;
  }
  $("upload-text").textContent = "checking the scan…";
  const parts = etags.every(Boolean) ? { parts: etags.map((etag, i) => ({ number: i + 1, etag })) } : {};
  return api(up.complete_url, { method: "POST", headers: json, body: JSON.stringify(parts) });
}
// a phone shows what happens after a press: the element scrolled into view (no jump when it is already there)
function reveal(el) { if (el && el.scrollIntoView) el.scrollIntoView({ block: "nearest", behavior: "auto" }); }
const QUICK_POLL_MS = 250, QUICK_FOR_MS = 10000, POLL_MS = 1000;
function follow(id) {
  clearTimeout(polling);
  if (id !== current) clearResult(); // nothing of another job stays on the page (its model, AR files, links)
  current = id;
  const mine = ++following; // a request still in flight from an earlier follow() ends its poll when it returns
  $("job-box").hidden = false; $("result-box").hidden = true; $("job-error").hidden = true;
  $("job-id").textContent = id; $("cancel").hidden = false;
  $("job-state").textContent = "asking…"; $("job-bar").value = 0; $("job-box").dataset.state = "";
  for (const li of $("jobs").children) li.classList.toggle("current", li.dataset.job === id);
  reveal($("job-box"));
  const since = Date.now();
  const tick = async () => {
    let job = null, error = null;
    try { job = await api(`/v1/jobs/${id}`); } catch (e) { error = e; }
    if (mine !== following) return;
    if (error) $("job-state").textContent = error.message;
    if (job) {
      show(job);
      if (["succeeded", "failed", "cancelled"].includes(job.state) && job.stage !== "orienting") { loadJobs(); return; }
    }
    // a young job is asked about four times a second (a job of a few seconds shows its stages), then once a second
    polling = setTimeout(tick, Date.now() - since < QUICK_FOR_MS ? QUICK_POLL_MS : POLL_MS);
  };
  tick();
}
// a job's state in words: a percentage only while it runs or when it is done; a job that failed says what failed
function stateText(job) {
  if (job.state === "failed") return job.stage ? `failed (while ${job.stage})` : "failed";
  if (job.state === "cancelled") return "cancelled";
  const stage = (job.state === "running" || job.stage === "orienting") && job.stage ? ` (${job.stage})` : "";
  return `${job.state}${stage}: ${job.progress.toFixed(0)} %`;
}
function failureText(error) {
  if (!error) return "It did not work (no reason was given).";
  if (isNoSpacing(error.code, error.message)) return `It did not work. ${NO_SPACING}`;
  const message = String(error.message || error.code || "").replace(/\.$/, "");
  return `It did not work: ${message}.`;
}
let lastJob = null; // the job resource shown last (the placement compares with it)
function show(job) {
  lastJob = job;
  const ended = job.state === "failed" || job.state === "cancelled";
  $("job-bar").value = ended ? 0 : job.progress;
  $("job-bar").hidden = ended;
  $("job-state").textContent = stateText(job);
  $("job-box").dataset.state = job.state;
  const active = job.state === "queued" || job.state === "running";
  $("cancel").hidden = !active;
  $("job-error").hidden = true;
  if (job.state === "failed") {
    $("job-error").hidden = false; $("job-error").textContent = failureText(job.error);
    $("job-error").dataset.code = (job.error && job.error.code) || "";
    if (job.error && isNoSpacing(job.error.code, job.error.message)) askForSpacing(); else reveal($("job-error"));
  }
  if (job.state === "succeeded" && job.error) { // a re-orientation that failed: the model is unchanged
    $("job-error").hidden = false; $("job-error").textContent = `It could not be turned: ${job.error.message}`;
  }
  if (job.state === "cancelled") { $("job-error").hidden = false; $("job-error").textContent = "Cancelled: its files were removed."; }
  if (job.state === "succeeded") result(job);
}
// the viewer's sources, the table, the links and the QR code: emptied when another job is shown, so nothing of the
// previous job (its model, its poster, its iOS AR file) can stay
function setSource(viewer, name, url) { if (url) viewer.setAttribute(name, url); else viewer.removeAttribute(name); }
function clearResult() {
  const viewer = $("viewer");
  for (const name of ["src", "ios-src", "poster"]) viewer.removeAttribute(name);
  viewer.dataset.shown = ""; viewer.dataset.job = ""; viewer.dataset.loaded = ""; viewer.dataset.arSrc = "";
  $("facts").tBodies[0].replaceChildren(); $("qr").replaceChildren(); $("share-url").value = "";
  $("model-warnings").replaceChildren(); $("model-warnings").hidden = true;
  $("defect-text").hidden = true; $("labels-box").hidden = true; $("labels-list").replaceChildren();
  $("orient-state").textContent = ""; $("job-error").hidden = true; $("job-bar").hidden = false;
}
function result(job) {
  const outs = Object.fromEntries(job.outputs.map((o) => [o.kind, o]));
  const viewer = $("viewer");
  const shown = `${job.id}:${JSON.stringify(job.params && job.params.orient || {})}`;
  viewer.dataset.arSrc = outs.ar ? outs.ar.url : "";
  $("orient-tools").dataset.busy = job.stage === "orienting" ? "yes" : "";
  if (job.stage === "orienting") { $("orient-state").textContent = "placing the model…"; placeControls(job, true); return; }
  if (viewer.dataset.shown !== shown) {
    viewer.dataset.shown = shown; viewer.dataset.job = job.id; viewer.dataset.loaded = "";
    $("place-box").hidden = true; // until its frame is read (a DICOM series, a defect or label job: not placed here)
    // every source of the viewer is this job's, or none: the model, iOS's AR file, the poster while it loads
    setSource(viewer, "ios-src", outs.ar_ios && outs.ar_ios.url);
    setSource(viewer, "poster", outs.preview && outs.preview.url);
    setSource(viewer, "src", (outs.phone || outs.model || {}).url);
    showFrame(job, outs.report);
    showDefect(job, outs.defect);
    showLabels(job, outs.labels ? outs.report : null);
    $("result-box").hidden = false;
    reveal(viewer); // a finished job's model comes into view (once, not at every poll)
  }
  placeControls(job, false);
  $("facts").tBodies[0].replaceChildren(...job.outputs.map(fileRow));
  const phone = outs.phone;
  $("share-url").value = phone ? phone.url : "";
  $("qr").replaceChildren(...(phone && window.qrcode ? [qrSvg(phone.url)] : []));
  $("result-box").hidden = false;
}
// one output file: its name, what it is for, triangles, size and a download link, all as text and attributes
function fileRow(o) {
  const tr = document.createElement("tr");
  const cell = (text, cls) => { const td = document.createElement("td"); td.textContent = text; if (cls) td.className = cls; return td; };
  const link = document.createElement("a");
  link.className = "button download"; link.href = o.url; link.download = o.name; link.dataset.name = o.name;
  link.textContent = "Download";
  const last = document.createElement("td"); last.append(link);
  tr.append(cell(o.name), cell(o.purpose || o.kind), cell(o.triangles == null ? "" : o.triangles.toLocaleString("en"), "num"),
    cell(human(o.bytes), "num"), last);
  return tr;
}
// the QR code as SVG elements (no markup string: nothing is parsed as HTML)
function qrSvg(text) {
  const qr = qrcode(0, "L"); qr.addData(text); qr.make();
  const n = qr.getModuleCount(), ns = "http://www.w3.org/2000/svg";
  const svg = document.createElementNS(ns, "svg");
  svg.setAttribute("viewBox", `-2 -2 ${n + 4} ${n + 4}`); svg.setAttribute("role", "img");
  svg.setAttribute("aria-label", "QR code of the phone link");
  const bg = document.createElementNS(ns, "rect");
  for (const [k, v] of [["x", -2], ["y", -2], ["width", n + 4], ["height", n + 4], ["fill", "#fff"]]) bg.setAttribute(k, v);
  let d = "";
  for (let r = 0; r < n; r++) for (let c = 0; c < n; c++) if (qr.isDark(r, c)) d += `M${c} ${r}h1v1h-1z`;
  const path = document.createElementNS(ns, "path");
  path.setAttribute("d", d); path.setAttribute("fill", "#000");
  svg.append(bg, path);
  return svg;
}

// --- where the patient is: direction labels on the model, and turning it (POST /v1/jobs/{id}/orient) ----------
// the glTF files are in the patient frame of the report: +Y superior, +Z anterior, +X the patient's left
const DIRECTIONS = { s: [0, 1, 0], i: [0, -1, 0], a: [0, 0, 1], p: [0, 0, -1], l: [1, 0, 0], r: [-1, 0, 0] };
function placeLabels() {
  const viewer = $("viewer");
  const d = viewer.getDimensions ? viewer.getDimensions() : null;
  if (!d) return;
  const half = [d.x / 2, d.y / 2, d.z / 2];
  for (const [name, v] of Object.entries(DIRECTIONS)) {
    const at = v.map((c, k) => c * half[k] * 1.12);
    const el = viewer.querySelector(`[slot="hotspot-${name}"]`);
    if (el) { el.dataset.position = at.map((c) => c.toFixed(4)).join(" "); el.dataset.normal = v.join(" "); }
    viewer.updateHotspot({ name: `hotspot-${name}`, position: at.join(" "), normal: v.join(" ") });
  }
}
async function showFrame(job, report) {
  const stack = !job.params || !job.params.orient ? null : job.params.orient;
  $("orient-tools").dataset.job = job.id;
  let frame = null, warnings = [];
  if (report) {
    try { const r = await (await fetch(report.url)).json(); frame = r.frame; warnings = r.warnings || []; } catch (e) { frame = null; }
  }
  if ($("viewer").dataset.job !== job.id) return; // another job is shown by now
  // what the engine doubts about this model (a skin-like surface, a voxel size that looks swapped): said, not hidden
  const box = $("model-warnings");
  box.replaceChildren(...warnings.map((w) => { const li = document.createElement("li"); li.dataset.code = w.code; li.textContent = w.message; return li; }));
  box.hidden = warnings.length === 0;
  const dicom = frame && String(frame.placed_by || "").startsWith("DICOM");
  // a DICOM series is placed by its headers; a defect template's side and measures belong to its orientation
  const fixed = dicom || !!(job.params && job.params.defect) || isLabelJob(job);
  $("place-box").hidden = fixed;
  $("place-box").dataset.fixed = fixed ? "yes" : "";
  $("frame-text").textContent = frame
    ? `S/I: head/feet, A/P: front/back, L/R: the patient's left/right. Placed by ${frame.placed_by}.`
    : "S/I: head/feet, A/P: front/back, L/R: the patient's left/right.";
  $("frame-text").dataset.placedBy = frame ? frame.placed_by : "";
  $("orient-state").textContent = fixed || !stack ? "" : `Now: ${placeWords(stack)}.`;
}
// the defect's answer (defect.json): the template's size beside the model, or why none was made
async function showDefect(job, defect) {
  const box = $("defect-text");
  box.hidden = !defect; box.dataset.found = ""; box.textContent = "";
  if (!defect) return;
  let d = null;
  try { d = await (await fetch(defect.url)).json(); } catch (e) { box.textContent = "The defect's report could not be read."; return; }
  if ($("viewer").dataset.job !== job.id) return; // another job is shown by now
  box.dataset.found = d.found ? "yes" : "no";
  if (!d.found) { box.textContent = `No defect template: ${d.message}`; return; }
  const f = d.defect, mm = (v) => v.toLocaleString("en", { maximumFractionDigits: 0 });
  box.textContent = `Defect template (blue): the patient's ${f.side}, ${mm(f.volume_mm3)} mm³, ` +
    `${f.extent_lps_mm.size.map((v) => v.toFixed(0)).join(" × ")} mm, rim gap ${f.rim.gap_mm.toFixed(1)} mm. ` +
    "Download implant.stl to print it (same frame as model.stl).";
}
// --- a label job (a segmentation, or a CT's pieces): one node per label, each with a checkbox -----------------
// a label job is placed by its label map (or is a CT's pieces): it has labels.zip (kind "labels") and is not turned
function isLabelJob(job) { return (job.outputs || []).some((o) => o.kind === "labels"); }
// the labels from report.json (name, colour, volume, faces), each a checkbox that shows or hides its node: the
// node's material (named as the label) is cut away (alpha mask) when unticked, opaque in its colour when ticked
async function showLabels(job, report) {
  const box = $("labels-box"), list = $("labels-list");
  box.hidden = !report; list.replaceChildren(); box.dataset.count = "";
  if (!report) return;
  let rows = [];
  try { rows = (await (await fetch(report.url)).json()).labels || []; } catch (e) { return; }
  if ($("viewer").dataset.job !== job.id) return; // another job is shown by now
  list.replaceChildren(...rows.map(labelRow));
  box.dataset.count = String(rows.length);
}
function labelRow(row) {
  const li = document.createElement("li");
  const check = document.createElement("input");
  check.type = "checkbox"; check.checked = true; check.dataset.label = row.name;
  check.onchange = () => setLabelVisible(row.name, row.color, check.checked);
  const swatch = document.createElement("span");
  swatch.className = "swatch";
  swatch.style.background = `rgb(${row.color.map((c) => Math.round(c * 255)).join(",")})`;
  const text = document.createElement("span");
  text.textContent = ` ${row.name}: ${Math.round(row.volume_mm3).toLocaleString("en")} mm³, ${row.faces.toLocaleString("en")} triangles`;
  const label = document.createElement("label");
  label.className = "check"; label.append(check, swatch, text);
  const stl = document.createElement("a"); // this label's STL alone (GET /v1/jobs/{id}/labels/{value}.stl)
  stl.href = "#"; stl.textContent = "STL"; stl.className = "label-stl"; stl.dataset.stl = String(row.value);
  stl.title = `download ${row.file.split("/").pop()} (watertight, mm)`;
  stl.onclick = async (event) => {
    event.preventDefault();
    try { save(await labelStl($("job-id").textContent, row.value), row.file.split("/").pop()); }
    catch (e) { stl.textContent = `STL: ${e.message}`; }
  };
  li.append(label, " ", stl);
  return li;
}
// one label's STL of a label job, fetched with the key (the API serves it out of labels.zip)
async function labelStl(jobId, value) {
  const resp = await fetch(`/v1/jobs/${jobId}/labels/${value}.stl`, { headers: headers() });
  if (!resp.ok) throw new Error(((await resp.json().catch(() => null)) || {}).detail || `${resp.status}`);
  return resp.blob();
}
function save(blob, name) {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob); a.download = name; a.click();
  setTimeout(() => URL.revokeObjectURL(a.href), 60000);
}
function setLabelVisible(name, color, visible) {
  const model = $("viewer").model;
  const material = model && model.getMaterialByName ? model.getMaterialByName(name) : null;
  if (!material) return false;
  material.pbrMetallicRoughness.setBaseColorFactor([...color, visible ? 1 : 0]);
  material.setAlphaMode(visible ? "OPAQUE" : "MASK"); // OPAQUE drops the cutoff (model-viewer 4.4)
  if (!visible) material.setAlphaCutoff(0.5);
  return true;
}
// --- placing the model: absolute choices (the stack's orientation, as the upload form and `bonemesh orient` say it),
// never toggles: the choice already published is checked, choosing it again sends nothing
function stackOf(job) {
  return { first_slice: "superior", flip_lr: false, flip_ap: false, ...(job.params && job.params.orient || {}) };
}
function placeWords(o) {
  return `head end (S) = the ${o.first_slice === "superior" ? "first" : "last"} slice, front (A) = the `
    + `${o.flip_ap ? "bottom" : "top"} of each image, the patient's left (L) = the image's ${o.flip_lr ? "left" : "right"}`;
}
function chosenPlace() {
  const value = (name) => (document.querySelector(`input[name="${name}"]:checked`) || {}).value;
  return { first_slice: value("place-first"), flip_ap: value("place-ap") === "posterior", flip_lr: value("place-lr") === "left" };
}
function samePlace(a, b) { return a.first_slice === b.first_slice && a.flip_lr === b.flip_lr && a.flip_ap === b.flip_ap; }
// the radios show the job's published orientation (when it changed, or another job is shown)
function placeControls(job, busy) {
  const now = stackOf(job), box = $("place-box"), key = `${job.id}:${JSON.stringify(now)}`;
  if (box.dataset.shown !== key) {
    box.dataset.shown = key;
    const check = (name, value) => { for (const r of document.getElementsByName(name)) r.checked = r.value === value; };
    check("place-first", now.first_slice); check("place-ap", now.flip_ap ? "posterior" : "anterior");
    check("place-lr", now.flip_lr ? "left" : "right");
  }
  box.dataset.busy = busy ? "yes" : "";
  for (const input of box.querySelectorAll("input")) input.disabled = busy;
  placeChanged(job);
}
// the button says what pressing it does; it is off while the choice is the published one
function placeChanged(job = lastJob) {
  const button = $("place-apply");
  if (!job) { button.disabled = true; return; }
  const now = stackOf(job), want = chosenPlace(), busy = $("place-box").dataset.busy === "yes";
  const same = samePlace(now, want);
  button.disabled = busy || same;
  button.textContent = same ? "Placed so" : "Place it so";
  button.title = same ? "the model is placed as chosen" : `write every file again with ${placeWords(want)}`;
}
async function place() {
  const job = await api(`/v1/jobs/${current}`);
  const want = chosenPlace();
  if (samePlace(stackOf(job), want)) { placeChanged(job); return; } // nothing to change: nothing sent
  $("place-apply").disabled = true;
  try {
    show(await api(`/v1/jobs/${job.id}/orient`, { method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(want) }));
    follow(job.id);
  } catch (e) { $("orient-state").textContent = e.message; placeChanged(job); }
}
// the region's example in the order of its units: voxel indices z, y, x; mm in the patient frame x, y, z
const ROI_HINTS = {
  voxels: "e.g. 0:60, 0:256, 0:256 as z, y, x voxel indices",
  mm: "e.g. -90:0, -120:100, 0:80 as x, y, z mm (LPS)",
};
function roiHint() { $("roi").placeholder = ROI_HINTS[$("roi-units").value]; }

const isAndroid = () => /Android/i.test(navigator.userAgent);

// --- the key's recent jobs -----------------------------------------------------------------------------------
async function loadJobs() {
  if (!key()) return;
  let list;
  try { list = await api("/v1/jobs?limit=20"); } catch (e) {
    const li = document.createElement("li"); li.className = "error"; li.textContent = e.message;
    $("jobs").replaceChildren(li); return;
  }
  $("jobs").replaceChildren(...list.items.map(jobRow));
}
// one job of the list: its thumbnail, upload name, state and time, all as text
function jobRow(job) {
  const li = document.createElement("li");
  li.dataset.job = job.id; li.tabIndex = 0; li.classList.toggle("current", job.id === current);
  const thumb = (job.outputs || []).find((o) => o.kind === "preview");
  const img = document.createElement(thumb ? "img" : "span");
  if (thumb) { img.src = thumb.url; img.alt = "preview"; } else img.className = "thumb";
  const text = document.createElement("span");
  const name = document.createElement("b"); name.textContent = job.upload_name || job.id;
  const state = document.createElement("span"); state.className = `state-${job.state}`; state.textContent = job.state;
  text.append(name, " · ", state, ` · ${new Date(job.created_at).toLocaleString()}`);
  li.append(img, text);
  li.onclick = () => follow(job.id);
  li.onkeydown = (e) => { if (e.key === "Enter" || e.key === " ") { e.preventDefault(); follow(job.id); } };
  return li;
}

// files dropped anywhere on the page are taken as the scan (a browser would otherwise open them in place of the page)
async function dropped(e) {
  e.preventDefault(); $("drop").classList.remove("over");
  const items = [...(e.dataTransfer.items || [])];
  const entries = items.map((i) => i.webkitGetAsEntry && i.webkitGetAsEntry()).filter(Boolean);
  const files = entries.some((x) => x.isDirectory) ? (await Promise.all(entries.map((x) => entriesOf(x)))).flat()
    : [...e.dataTransfer.files];
  reveal($("drop"));
  pick(files);
}

window.addEventListener("DOMContentLoaded", () => {
  showKeyState();
  if (key()) { $("api-key").value = key(); loadJobs(); }
  $("key-save").onclick = () => { setKey($("api-key").value.trim(), $("key-remember").checked); loadJobs(); };
  $("key-remember").onchange = () => { if (key()) setKey(key(), $("key-remember").checked); };
  $("key-forget").onclick = () => { setKey("", false); $("api-key").value = ""; $("jobs").replaceChildren(); };
  $("file-input").onchange = (e) => pick([...e.target.files]);
  $("folder-input").onchange = (e) => pick([...e.target.files]);
  const drop = $("drop");
  window.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  window.addEventListener("dragleave", (e) => { if (!e.relatedTarget) drop.classList.remove("over"); });
  window.addEventListener("drop", dropped);
  $("start").onclick = upload;
  $("cancel").onclick = async () => { try { show(await api(`/v1/jobs/${current}/cancel`, { method: "POST" })); } catch (e) { alert(e.message); } };
  $("refresh").onclick = loadJobs;
  $("share-link").onclick = async () => {
    const url = $("share-url").value;
    if (navigator.share) { try { await navigator.share({ title: "bone model", url }); return; } catch (e) { /* fall back */ } }
    $("share-url").select(); navigator.clipboard && navigator.clipboard.writeText(url);
  };
  const viewer = $("viewer");
  viewer.addEventListener("load", () => { viewer.dataset.loaded = "yes"; placeLabels(); });
  $("place-box").addEventListener("change", () => placeChanged());
  $("roi-units").addEventListener("change", roiHint);
  roiHint();
  $("place-apply").onclick = () => { if (current) place(); };
  // Android's Scene Viewer opens model-viewer's src: give it ar.glb (plain glTF; it cannot open Draco's phone.glb)
  $("ar-button").addEventListener("click", () => {
    const ar = viewer.dataset.arSrc;
    if (isAndroid() && ar && viewer.getAttribute("src") !== ar) viewer.setAttribute("src", ar);
  });
  viewer.addEventListener("error", (e) => { viewer.dataset.loaded = "error"; console.error("viewer", e.detail); });
});
