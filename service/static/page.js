// The bonemesh page: key in sessionStorage (never in a URL), upload with progress, job polling, cancel,
// the 3D view (<model-viewer>, decoders served by this server), downloads, QR code and the key's recent jobs.
"use strict";
const $ = (id) => document.getElementById(id);
const KEY = "bonemesh-api-key";
const FOR = {
  "model.stl": "3D printing (mm)", "model.glb": "full-detail viewing", "phone.glb": "the phone app (Draco)",
  "phone_meshopt.glb": "three.js / model-viewer without Draco", "ar.glb": "Android AR (Scene Viewer)",
  "model.usdz": "iPhone / iPad AR (Quick Look)", "preview.png": "thumbnail", "report.json": "what was done",
  "surface_open.stl": "open surface (mm)",
};
let picked = null; // {name, blob}
let polling = null;
let current = null;
let following = 0; // which call of follow() the running poll belongs to

function key() { return sessionStorage.getItem(KEY) || ""; }
function headers() { return { "X-API-Key": key() }; }
function human(bytes) {
  const u = ["B", "kB", "MB", "GB"]; let i = 0;
  while (bytes >= 1000 && i < u.length - 1) { bytes /= 1000; i++; }
  return `${bytes.toFixed(i ? 1 : 0)} ${u[i]}`;
}
async function api(path, options = {}) {
  const resp = await fetch(path, { ...options, headers: { ...headers(), ...(options.headers || {}) } });
  const body = resp.status === 204 ? null : await resp.json().catch(() => null);
  if (!resp.ok) throw new Error((body && body.detail) || `${resp.status} ${resp.statusText}`);
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
async function pick(files) {
  files = files.filter((f) => !f.name.startsWith("."));
  if (!files.length) return;
  const single = files.length === 1 && /\.(zip|tar|tgz|tar\.gz)$/i.test(files[0].name);
  $("picked").textContent = single ? `${files[0].name} (${human(files[0].size)})` : `${files.length} files: packing…`;
  picked = single ? { name: files[0].name, blob: files[0] } : { name: "slices.zip", blob: await zipFiles(files) };
  if (!single) $("picked").textContent = `${files.length} files (${human(picked.blob.size)} as a zip)`;
}

// --- upload, then follow the job ----------------------------------------------------------------------------
function params() {
  const p = {}; const kind = $("level-kind").value;
  if (kind === "iso") p.iso = Number($("iso").value);
  else if (kind !== "auto") p.preset = kind;
  if ($("hu-offset").value) p.hu_offset = Number($("hu-offset").value);
  const spacing = $("spacing").value.split(/[ ,;]+/).filter(Boolean).map(Number);
  if (spacing.length === 3) p.spacing = spacing;
  if ($("reduction").value) p.reduction = Number($("reduction").value);
  return p;
}
function upload() {
  if (!key()) { alert("Enter your API key first."); return; }
  if (!picked) { alert("Choose a scan first."); return; }
  const form = new FormData();
  form.append("file", picked.blob, picked.name);
  form.append("params", JSON.stringify(params()));
  const xhr = new XMLHttpRequest();
  xhr.open("POST", "/v1/jobs");
  xhr.setRequestHeader("X-API-Key", key());
  $("upload-progress").hidden = false; $("start").disabled = true;
  xhr.upload.onprogress = (e) => { if (e.lengthComputable) {
    $("upload-bar").value = (100 * e.loaded) / e.total; $("upload-text").textContent = `uploading ${human(e.loaded)} of ${human(e.total)}`; } };
  xhr.onload = () => {
    $("start").disabled = false;
    let body = null; try { body = JSON.parse(xhr.responseText); } catch (e) { /* not JSON */ }
    if (xhr.status !== 202) { $("upload-text").textContent = `refused: ${(body && body.detail) || xhr.status}`; return; }
    $("upload-bar").value = 100; $("upload-text").textContent = "uploaded";
    follow(body.id); loadJobs();
  };
  xhr.onerror = () => { $("start").disabled = false; $("upload-text").textContent = "the upload failed (network)"; };
  xhr.send(form);
}
const QUICK_POLL_MS = 250, QUICK_FOR_MS = 10000, POLL_MS = 1000;
function follow(id) {
  clearTimeout(polling); current = id;
  const mine = ++following; // a request still in flight from an earlier follow() ends its poll when it returns
  $("job-box").hidden = false; $("result-box").hidden = true; $("job-error").hidden = true;
  $("job-id").textContent = id; $("cancel").hidden = false;
  const since = Date.now();
  const tick = async () => {
    let job = null, error = null;
    try { job = await api(`/v1/jobs/${id}`); } catch (e) { error = e; }
    if (mine !== following) return;
    if (error) $("job-state").textContent = error.message;
    if (job) {
      show(job);
      if (["succeeded", "failed", "cancelled"].includes(job.state)) { loadJobs(); return; }
    }
    // a young job is asked about four times a second (a job of a few seconds shows its stages), then once a second
    polling = setTimeout(tick, Date.now() - since < QUICK_FOR_MS ? QUICK_POLL_MS : POLL_MS);
  };
  tick();
}
function show(job) {
  $("job-bar").value = job.progress;
  const stage = job.state === "running" && job.stage ? ` (${job.stage})` : "";
  $("job-state").textContent = `${job.state}${stage}: ${job.progress.toFixed(0)} %`;
  $("job-box").dataset.state = job.state;
  const active = job.state === "queued" || job.state === "running";
  $("cancel").hidden = !active;
  if (job.state === "failed") { $("job-error").hidden = false; $("job-error").textContent = `It did not work: ${job.error.message}`; }
  if (job.state === "cancelled") { $("job-error").hidden = false; $("job-error").textContent = "Cancelled: its files were removed."; }
  if (job.state === "succeeded") result(job);
}
function result(job) {
  const outs = Object.fromEntries(job.outputs.map((o) => [o.name, o]));
  const viewer = $("viewer");
  if (viewer.dataset.job !== job.id) {
    viewer.dataset.job = job.id; viewer.dataset.loaded = "";
    if (outs["model.usdz"]) viewer.setAttribute("ios-src", outs["model.usdz"].url);
    viewer.setAttribute("src", (outs["phone.glb"] || outs["model.glb"]).url);
  }
  const rows = job.outputs.map((o) => `<tr><td>${o.name}</td><td>${FOR[o.name] || o.kind}</td>
    <td>${o.triangles == null ? "" : o.triangles.toLocaleString("en")}</td><td>${human(o.bytes)}</td>
    <td><a class="button download" href="${o.url}" download="${o.name}" data-name="${o.name}">Download</a></td></tr>`);
  $("facts").tBodies[0].innerHTML = rows.join("");
  const phone = outs["phone.glb"];
  if (phone) {
    $("share-url").value = phone.url;
    if (window.qrcode) { const qr = qrcode(0, "L"); qr.addData(phone.url); qr.make(); $("qr").innerHTML = qr.createSvgTag(4, 0); }
  }
  $("result-box").hidden = false;
}

// --- the key's recent jobs -----------------------------------------------------------------------------------
async function loadJobs() {
  if (!key()) return;
  let list;
  try { list = await api("/v1/jobs?limit=20"); } catch (e) { $("jobs").innerHTML = `<li class="error">${e.message}</li>`; return; }
  $("jobs").innerHTML = "";
  for (const job of list.items) {
    const li = document.createElement("li");
    const thumb = (job.outputs || []).find((o) => o.name === "preview.png");
    const img = document.createElement(thumb ? "img" : "span");
    if (thumb) { img.src = thumb.url; img.alt = "preview"; } else { img.style.width = "56px"; }
    const text = document.createElement("span");
    text.innerHTML = `<b>${job.upload_name.replace(/[<>&]/g, "")}</b> · <span class="state-${job.state}">${job.state}</span>`
      + ` · ${new Date(job.created_at).toLocaleString()}`;
    li.append(img, text); li.onclick = () => follow(job.id);
    $("jobs").append(li);
  }
}

window.addEventListener("DOMContentLoaded", () => {
  if (key()) { $("api-key").value = key(); $("key-state").textContent = "key set for this tab"; loadJobs(); }
  $("key-save").onclick = () => { sessionStorage.setItem(KEY, $("api-key").value.trim()); $("key-state").textContent = "key set for this tab"; loadJobs(); };
  $("file-input").onchange = (e) => pick([...e.target.files]);
  $("folder-input").onchange = (e) => pick([...e.target.files]);
  const drop = $("drop");
  drop.ondragover = (e) => { e.preventDefault(); drop.classList.add("over"); };
  drop.ondragleave = () => drop.classList.remove("over");
  drop.ondrop = async (e) => {
    e.preventDefault(); drop.classList.remove("over");
    const entries = [...e.dataTransfer.items].map((i) => i.webkitGetAsEntry && i.webkitGetAsEntry()).filter(Boolean);
    const files = entries.some((x) => x.isDirectory) ? (await Promise.all(entries.map((x) => entriesOf(x)))).flat() : [...e.dataTransfer.files];
    pick(files);
  };
  $("start").onclick = upload;
  $("cancel").onclick = async () => { try { show(await api(`/v1/jobs/${current}/cancel`, { method: "POST" })); } catch (e) { alert(e.message); } };
  $("refresh").onclick = loadJobs;
  $("share-link").onclick = async () => {
    const url = $("share-url").value;
    if (navigator.share) { try { await navigator.share({ title: "bone model", url }); return; } catch (e) { /* fall back */ } }
    $("share-url").select(); navigator.clipboard && navigator.clipboard.writeText(url);
  };
  const viewer = $("viewer");
  viewer.addEventListener("load", () => { viewer.dataset.loaded = "yes"; });
  viewer.addEventListener("error", (e) => { viewer.dataset.loaded = "error"; console.error("viewer", e.detail); });
});
