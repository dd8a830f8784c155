// The page's side of the HTTP API. The page asks the server only for what it shows and answers its limits:
// a 429 or 503 is waited out (its Retry-After, capped) and tried again, never shown as an empty result.
// Downloads go through fetch too (not a bare link), so a busy server is waited out and an error reads as a
// sentence on the page instead of a JSON file saved to disk.

const RETRY_CAP_S = 10;
export const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
export const busy = (status) => status === 429 || status === 503;

export function retryDelayS(r, tries) {
  const given = r ? Number(r.headers.get('Retry-After')) : NaN;
  return Math.min(RETRY_CAP_S, Number.isFinite(given) && given > 0 ? given : 0.5 * 2 ** tries);
}

export async function fetchPatiently(path, opts = {}, tries = 5) {
  for (let i = 0; ; i++) {
    const r = await fetch(path, opts);
    if (!busy(r.status) || i >= tries) return r;
    await sleep(1000 * retryDelayS(r, i));
  }
}

async function errorOf(r, what) {
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  const err = new Error((data && data.message) || `${what} answered HTTP ${r.status}`);
  err.status = r.status;
  return err;
}

export async function api(method, path, body) {
  const opts = { method, headers: {} };
  if (body !== undefined) { opts.body = JSON.stringify(body); opts.headers['Content-Type'] = 'application/json'; }
  const r = await fetchPatiently(path, opts);
  if (!r.ok) throw await errorOf(r, `${method} ${path}`);
  const text = await r.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch (e) { data = null; }
  return { data, headers: r.headers };
}

// --- downloads ----------------------------------------------------------------------------------------
export function saveBlob(blob, name) {
  const a = document.createElement('a');
  a.href = URL.createObjectURL(blob); a.download = name; a.hidden = true;
  document.body.appendChild(a); a.click(); a.remove();
  setTimeout(() => URL.revokeObjectURL(a.href), 60_000);
}

function attachmentName(r) {
  const m = /filename="?([^";]+)"?/.exec(r.headers.get('Content-Disposition') || '');
  return m ? m[1] : null;
}

/** GET `path` and save it under the server's file name (else `fallback`); throws the server's message. */
export async function download(path, fallback) {
  const r = await fetchPatiently(path);
  if (!r.ok) throw await errorOf(r, `GET ${path}`);
  const name = attachmentName(r) || fallback;
  saveBlob(await r.blob(), name);
  return name;
}
