// omis web view: jobs, a live job page, workers, and a job form, over the REST API (/v1).
// No framework and nothing loaded from elsewhere. Every API call sends the client token when
// one is stored (sessionStorage); a 401 asks for it. The job page reads Server-Sent Events with
// fetch() and a stream reader (an Authorization header cannot be given to the browser's built-in
// SSE client), and shows images through blob object URLs fetched with the same header.
'use strict';

const TOKEN_KEY = 'omis.client-token';
const TERMINAL = new Set(['done', 'failed', 'cancelled']);
const ACTIVE = new Set(['queued', 'running', 'paused']);
const SVG_NS = 'http://www.w3.org/2000/svg';

// ---- DOM helpers ----

/** Element `tag` with attributes (on* are listeners, `class`, `dataset`, others set as is)
 * and children (strings become text nodes; null and false are skipped). */
function h(tag, attrs, ...kids) {
  const el = tag.startsWith('svg:')
    ? document.createElementNS(SVG_NS, tag.slice(4))
    : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k.startsWith('on')) el.addEventListener(k.slice(2), v);
    else if (k === 'dataset') Object.assign(el.dataset, v);
    // Through the CSSOM: the page's Content-Security-Policy refuses style attributes.
    else if (k === 'style') el.style.cssText = v;
    else if (k === 'class' && !(el instanceof SVGElement)) el.className = v;
    else el.setAttribute(k, v === true ? '' : String(v));
  }
  for (const kid of kids.flat(Infinity)) {
    if (kid === null || kid === undefined || kid === false) continue;
    el.append(kid instanceof Node ? kid : document.createTextNode(String(kid)));
  }
  return el;
}

function fmtSeconds(s) {
  if (s === null || s === undefined || !isFinite(s)) return '—';
  if (s < 10) return `${s.toFixed(1)} s`;
  if (s < 60) return `${Math.round(s)} s`;
  if (s < 3600) return `${Math.floor(s / 60)} m ${String(Math.round(s % 60)).padStart(2, '0')} s`;
  return `${Math.floor(s / 3600)} h ${String(Math.floor((s % 3600) / 60)).padStart(2, '0')} m`;
}
const fmtRel = (x) => (x === null || x === undefined ? '—' : Number(x).toExponential(3));
const fmtClock = (unix) => (unix ? new Date(unix * 1000).toLocaleTimeString() : '—');
const short = (id) => String(id).slice(0, 8);
const stateBadge = (state, id) => h('span', { class: `state state-${state}`, id }, state);
const jobTitle = (j) => j.name || `job ${short(j.id)}`;
const sppText = (j) => (j.spp_target ? `${j.spp_done} / ${j.spp_target}` : `${j.spp_done}`);

// ---- the API, with the token ----

class ApiError extends Error {
  constructor(status, body) {
    const msg = body && body.error ? body.error : `HTTP ${status}`;
    super(body && body.field ? `${msg} (${body.field})` : msg);
    this.status = status;
    this.field = body && body.field;
  }
}

const token = () => sessionStorage.getItem(TOKEN_KEY);
let tokenPrompt = null;

/** Asks for the client token once for every call that is waiting on it. */
function askToken(message) {
  if (tokenPrompt) return tokenPrompt;
  tokenPrompt = new Promise((resolve) => {
    const dialog = document.getElementById('token-dialog');
    const form = document.getElementById('token-form');
    const input = document.getElementById('token-input');
    const err = document.getElementById('token-error');
    err.hidden = !message;
    err.textContent = message || '';
    input.value = '';
    const done = (ev) => {
      ev.preventDefault();
      const t = input.value.trim();
      if (!t) return;
      sessionStorage.setItem(TOKEN_KEY, t);
      form.removeEventListener('submit', done);
      dialog.close();
      updateTokenButton();
      tokenPrompt = null;
      resolve();
    };
    form.addEventListener('submit', done);
    dialog.showModal();
    input.focus();
  });
  return tokenPrompt;
}

function updateTokenButton() {
  document.getElementById('forget').hidden = !token();
}

/** fetch() on the API with the token; a 401 asks for the token and tries again. */
async function api(path, opts = {}) {
  for (;;) {
    const sent = token();
    const headers = new Headers(opts.headers || {});
    if (sent) headers.set('Authorization', `Bearer ${sent}`);
    const r = await fetch(path, { ...opts, headers, cache: 'no-store' });
    if (r.status !== 401) return r;
    const body = await r.json().catch(() => null);
    if (token() !== sent) continue; // another call got a new token meanwhile
    if (sent) sessionStorage.removeItem(TOKEN_KEY);
    updateTokenButton();
    await askToken(sent ? `The coordinator refused that token: ${body && body.error}` : null);
  }
}

async function apiJson(path, opts = {}) {
  const r = await api(path, opts);
  const body = await r.json().catch(() => null);
  if (!r.ok) throw new ApiError(r.status, body);
  return body;
}

// Every job `query` selects (GET /v1/jobs, page after page), oldest first.
async function allJobs(opts = {}, query = '') {
  const jobs = [];
  let after = null;
  for (;;) {
    const q = [query, after === null ? '' : `after=${encodeURIComponent(after)}`].filter(Boolean).join('&');
    const page = await apiJson(q ? `/v1/jobs?${q}` : '/v1/jobs', opts);
    jobs.push(...page.jobs);
    if (page.next == null || page.next === after) return { jobs };
    after = page.next;
  }
}

async function apiBlob(path, signal) {
  const r = await api(path, { signal });
  if (!r.ok) throw new ApiError(r.status, await r.json().catch(() => null));
  return r.blob();
}

/** Follows a job's events until a final one (or `signal`): parses the event stream itself and
 * reconnects with Last-Event-ID after a break, unless `isOver()` says the job has ended.
 * `onEvent(type, data, id)` hears each event; `onState` hears 'live' / 'reconnecting'. */
async function followEvents(id, onEvent, onState, isOver, signal) {
  let lastId = null;
  let backoff = 500;
  while (!signal.aborted) {
    const conn = new AbortController();
    const stop = () => conn.abort();
    signal.addEventListener('abort', stop);
    // The server sends a comment every 15 s: a silent minute means a dead connection.
    let watchdog = setTimeout(stop, 60000);
    let ended = false;
    try {
      const headers = { Accept: 'text/event-stream' };
      if (lastId) headers['Last-Event-ID'] = lastId;
      const r = await api(`/v1/jobs/${encodeURIComponent(id)}/events`, { headers, signal: conn.signal });
      if (!r.ok) throw new ApiError(r.status, await r.json().catch(() => null));
      onState('live');
      backoff = 500;
      const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
      let buf = '';
      let ev = { type: '', data: [], id: null };
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        clearTimeout(watchdog);
        watchdog = setTimeout(stop, 60000);
        buf += value;
        let m;
        while ((m = /\r\n|\r|\n/.exec(buf))) {
          // A lone \r at the end may be the first half of \r\n: wait for more.
          if (m[0] === '\r' && m.index === buf.length - 1) break;
          const line = buf.slice(0, m.index);
          buf = buf.slice(m.index + m[0].length);
          if (line === '') {
            if (ev.id !== null) lastId = ev.id;
            if (ev.data.length) {
              const type = ev.type || 'message';
              let data = null;
              try {
                data = JSON.parse(ev.data.join('\n'));
              } catch (e) {
                data = { text: ev.data.join('\n') };
              }
              onEvent(type, data, lastId);
              if (TERMINAL.has(type)) ended = true;
            }
            ev = { type: '', data: [], id: null };
            continue;
          }
          if (line.startsWith(':')) continue; // comment (keep-alive)
          const colon = line.indexOf(':');
          const field = colon < 0 ? line : line.slice(0, colon);
          let val = colon < 0 ? '' : line.slice(colon + 1);
          if (val.startsWith(' ')) val = val.slice(1);
          if (field === 'event') ev.type = val;
          else if (field === 'data') ev.data.push(val);
          else if (field === 'id' && !val.includes('\0')) ev.id = val;
        }
        if (ended) {
          reader.cancel().catch(() => {});
          break;
        }
      }
    } catch (e) {
      if (signal.aborted) return;
      if (e instanceof ApiError && e.status === 404) throw e;
    } finally {
      clearTimeout(watchdog);
      signal.removeEventListener('abort', stop);
    }
    if (ended || signal.aborted) return;
    if (await isOver().catch(() => false)) return;
    onState('reconnecting');
    await sleep(backoff, signal);
    backoff = Math.min(backoff * 2, 8000);
  }
}

function sleep(ms, signal) {
  return new Promise((resolve) => {
    const t = setTimeout(resolve, ms);
    if (signal) signal.addEventListener('abort', () => { clearTimeout(t); resolve(); }, { once: true });
  });
}

/** Calls `fn` now and every `ms` after it settles, until `signal`. */
async function every(ms, signal, fn) {
  while (!signal.aborted) {
    try {
      await fn();
    } catch (e) {
      if (!signal.aborted) console.warn(e);
    }
    await sleep(ms, signal);
  }
}

/** Runs `fn` once at a time; calls made while it runs make it run once more after. */
function coalesce(fn) {
  let running = false;
  let again = false;
  return async function run() {
    if (running) {
      again = true;
      return;
    }
    running = true;
    try {
      do {
        again = false;
        await fn();
      } while (again);
    } catch (e) {
      console.warn(e);
    } finally {
      running = false;
    }
  };
}

/** Saves a file of the API (fetched with the token) under `name`. */
async function download(path, name) {
  const blob = await apiBlob(path);
  const url = URL.createObjectURL(blob);
  const a = h('a', { href: url, download: name });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// ---- views ----

const view = () => document.getElementById('view');

function showError(e) {
  view().replaceChildren(h('div', { class: 'panel error' }, String(e.message || e)));
}

// -- jobs list --

async function jobsView(signal) {
  document.title = 'omis: jobs';
  const body = h('tbody');
  const table = h('table', { id: 'jobs' },
    h('thead', {}, h('tr', {},
      h('th', {}, 'Job'), h('th', {}, 'Scene'), h('th', {}, 'State'), h('th', { class: 'num' }, 'spp'),
      h('th', { class: 'num' }, 'Passes'), h('th', { class: 'num' }, 'Elapsed'), h('th', { class: 'num' }, 'ETA'),
      h('th', { class: 'num' }, 'relMSE'), h('th', { class: 'num' }, 'Priority'), h('th', {}, 'Created'))),
    body);
  // The filter is the list's query (GET /v1/jobs?state=...&name=...): the coordinator selects.
  const stateFilter = h('select', { id: 'filter-state', 'aria-label': 'state' },
    h('option', { value: '' }, 'every state'),
    ...['queued', 'running', 'paused', 'done', 'failed', 'cancelled'].map((s) => h('option', { value: s }, s)),
    h('option', { value: 'queued,running,paused' }, 'not ended'));
  const nameFilter = h('input', { id: 'filter-name', type: 'search', placeholder: 'name contains', 'aria-label': 'name' });
  const query = () => {
    const q = new URLSearchParams();
    if (stateFilter.value) q.set('state', stateFilter.value);
    if (nameFilter.value.trim()) q.set('name', nameFilter.value.trim());
    return q.toString();
  };
  const refresh = async () => {
    const { jobs } = await allJobs({ signal }, query());
    jobs.sort((a, b) => b.created_at - a.created_at);
    if (!jobs.length) {
      body.replaceChildren(h('tr', {}, h('td', { colspan: 10, class: 'empty' }, query() ? 'No job matches the filter.' : 'No jobs yet. ', query() ? '' : h('a', { href: '#/submit' }, 'Submit one.'))));
      return;
    }
    body.replaceChildren(...jobs.map((j) => h('tr', { dataset: { id: j.id } },
      h('td', {}, h('a', { href: `#/jobs/${j.id}` }, jobTitle(j))),
      h('td', { class: 'mono' }, j.scene.main),
      h('td', {}, stateBadge(j.state)),
      h('td', { class: 'num' }, sppText(j)),
      h('td', { class: 'num' }, j.passes_total ? `${j.passes_done} / ${j.passes_total}` : j.passes_done),
      h('td', { class: 'num' }, fmtSeconds(j.elapsed_s)),
      h('td', { class: 'num' }, j.state === 'paused' ? 'paused' : ACTIVE.has(j.state) ? fmtSeconds(j.eta_s) : '—'),
      h('td', { class: 'num' }, fmtRel(j.relmse)),
      h('td', { class: 'num' }, String(j.priority ?? 0)),
      h('td', {}, fmtClock(j.created_at)))));
  };
  const now = coalesce(refresh);
  stateFilter.addEventListener('change', now);
  nameFilter.addEventListener('input', now);
  view().replaceChildren(
    h('div', { class: 'job-head' }, h('h1', {}, 'Jobs'),
      h('div', { class: 'actions' }, stateFilter, nameFilter,
        h('a', { href: '#/submit' }, h('button', { class: 'primary', type: 'button' }, 'New job')))),
    table);
  await every(2000, signal, refresh);
}

// -- one job --

/** Row-major tiles of `size` covering `w` x `h` (the coordinator's order). */
function tileRect(i, w, hgt, size) {
  const cols = Math.ceil(w / size);
  const x0 = (i % cols) * size;
  const y0 = Math.floor(i / cols) * size;
  return [x0, y0, Math.min(x0 + size, w), Math.min(y0 + size, hgt)];
}

/** A log-log chart of relMSE against seconds, as an SVG element. */
function relmseChart(series) {
  const pts = series.filter((p) => p.relmse > 0 && p.seconds > 0).map((p) => [p.seconds, p.relmse]);
  const W = 480, H = 300, L = 62, R = 16, T = 16, B = 42;
  const svg = h('svg:svg', { viewBox: `0 0 ${W} ${H}`, class: 'chart', id: 'relmse-chart', role: 'img', 'aria-label': 'relMSE against time' });
  if (!pts.length) {
    svg.append(h('svg:text', { x: W / 2, y: H / 2, 'text-anchor': 'middle' }, 'relMSE appears after the first pass'));
    return svg;
  }
  const lx = pts.map((p) => Math.log10(p[0]));
  const ly = pts.map((p) => Math.log10(p[1]));
  let [x0, x1] = [Math.min(...lx), Math.max(...lx)];
  let [y0, y1] = [Math.min(...ly), Math.max(...ly)];
  if (x1 - x0 < 0.3) { const c = (x0 + x1) / 2; x0 = c - 0.15; x1 = c + 0.15; }
  if (y1 - y0 < 0.3) { const c = (y0 + y1) / 2; y0 = c - 0.15; y1 = c + 0.15; }
  const px = (v) => L + ((v - x0) / (x1 - x0)) * (W - L - R);
  const py = (v) => T + (1 - (v - y0) / (y1 - y0)) * (H - T - B);
  const ticks = (a, b) => {
    const out = [];
    for (let e = Math.floor(a); e <= Math.ceil(b); e++) {
      for (const m of b - a < 1.5 ? [1, 2, 5] : [1]) {
        const v = e + Math.log10(m);
        if (v >= a - 1e-9 && v <= b + 1e-9) out.push(v);
      }
    }
    return out;
  };
  const label = (v) => {
    const x = Math.pow(10, v);
    return x >= 0.01 && x < 1000 ? String(Number(x.toPrecision(2))) : x.toExponential(0);
  };
  for (const v of ticks(x0, x1)) {
    svg.append(h('svg:line', { class: 'grid', x1: px(v), x2: px(v), y1: T, y2: H - B }));
    svg.append(h('svg:text', { x: px(v), y: H - B + 16, 'text-anchor': 'middle' }, label(v)));
  }
  for (const v of ticks(y0, y1)) {
    svg.append(h('svg:line', { class: 'grid', x1: L, x2: W - R, y1: py(v), y2: py(v) }));
    svg.append(h('svg:text', { x: L - 6, y: py(v) + 4, 'text-anchor': 'end' }, label(v)));
  }
  svg.append(h('svg:line', { class: 'axis', x1: L, x2: W - R, y1: H - B, y2: H - B }));
  svg.append(h('svg:line', { class: 'axis', x1: L, x2: L, y1: T, y2: H - B }));
  svg.append(h('svg:text', { x: (L + W - R) / 2, y: H - 6, 'text-anchor': 'middle' }, 'seconds since start'));
  svg.append(h('svg:text', { x: 14, y: (T + H - B) / 2, 'text-anchor': 'middle', transform: `rotate(-90 14 ${(T + H - B) / 2})` }, 'relMSE'));
  const d = lx.map((v, i) => `${i ? 'L' : 'M'}${px(v).toFixed(1)},${py(ly[i]).toFixed(1)}`).join(' ');
  svg.append(h('svg:path', { class: 'line', d }));
  lx.forEach((v, i) => svg.append(h('svg:circle', { class: 'dot', cx: px(v), cy: py(ly[i]), r: 2.5 })));
  return svg;
}

/** The job page's task history: every attempt (failed ones first, with their errors), the
 * workers blocklisted for the job (each with a button that clears it) and why the job waits. */
function taskHistoryPanel(id, signal) {
  const path = `/v1/jobs/${encodeURIComponent(id)}`;
  const body = h('tbody');
  const blocked = h('ul', { class: 'blocklist', id: 'blocklist' });
  const waiting = h('p', { class: 'hint', id: 'waiting-for' });
  const panel = h('details', { class: 'panel', id: 'task-history' },
    h('summary', {}, 'Task history'),
    waiting, blocked,
    h('table', { class: 'history' },
      h('thead', {}, h('tr', {},
        h('th', {}, 'Task'), h('th', {}, 'Worker'), h('th', {}, 'Outcome'),
        h('th', { class: 'num' }, 'Seconds'), h('th', {}, 'Error'))),
      body));
  async function load() {
    const [st, page] = await Promise.all([
      apiJson(path, { signal }),
      apiJson(`${path}/tasks?limit=200`, { signal }),
    ]);
    waiting.textContent = st.waiting_for || '';
    blocked.replaceChildren(...(st.blocklisted_workers || []).map((b) => {
      const btn = h('button', { type: 'button' }, 'Clear');
      btn.addEventListener('click', async () => {
        btn.disabled = true;
        try {
          await apiJson(`${path}/blocklist/${encodeURIComponent(b.worker_id)}`, { method: 'DELETE' });
          await load();
        } catch (e) {
          alert(e.message);
          btn.disabled = false;
        }
      });
      return h('li', {}, 'blocklisted: ', h('span', { class: 'mono' }, short(b.worker_id)), ' ',
        h('span', { class: 'muted' }, b.reason), ' ', btn);
    }));
    body.replaceChildren(...page.attempts.map((a) => h('tr', { class: `outcome-${a.outcome}` },
      h('td', {}, a.kind === 'merge' ? `merge ${a.pass}/${a.tile}` : `pass ${a.pass} tile ${a.tile}`, ` #${a.attempt}`),
      h('td', { class: 'mono' }, short(a.worker_id)),
      h('td', {}, a.outcome),
      h('td', { class: 'num' }, a.seconds === null ? '…' : a.seconds.toFixed(2)),
      h('td', {}, a.error || ''))));
  }
  panel.addEventListener('toggle', () => { if (panel.open) load().catch(showError); });
  every(5000, signal, async () => { if (panel.open) await load(); }).catch(() => {});
  return panel;
}

async function jobView(signal, id) {
  const path = `/v1/jobs/${encodeURIComponent(id)}`;
  let st = await apiJson(path, { signal });
  let fetchedAt = performance.now();
  document.title = `omis: ${jobTitle(st)}`;

  // Tiles finished per pass not yet merged; the current pass is the lowest of those.
  const tilesDone = new Map();
  let currentPass = st.passes_done;
  let previewUrl = null;
  let errorUrl = null;
  let shownPass = null;
  let previewPass = st.passes_done - 1;
  let chartKey = null;
  signal.addEventListener('abort', () => {
    if (previewUrl) URL.revokeObjectURL(previewUrl);
    if (errorUrl) URL.revokeObjectURL(errorUrl);
  });

  const stateEl = h('span');
  const facts = h('dl', { class: 'facts' });
  // A sequence: one chip per frame, coloured by its state; the preview shows the chosen frame
  // (at first the last frame with a pass merged).
  const strip = h('div', { class: 'frame-strip', id: 'frame-strip', hidden: true });
  let chosenFrame = null;
  const previewFrame = () => {
    if (!st.frames) return null;
    if (chosenFrame !== null) return chosenFrame;
    const rendered = st.frames.filter((f) => f.passes_done > 0);
    return (rendered.length ? rendered[rendered.length - 1] : st.frames[0]).frame;
  };
  const img = h('img', { id: 'preview', alt: 'preview', hidden: true });
  const canvas = h('canvas', { id: 'tiles' });
  const placeholder = h('div', { class: 'placeholder' }, 'the preview appears after the first pass');
  const stage = h('div', { class: 'stage' }, placeholder, img, canvas);
  const caption = h('figcaption', { id: 'preview-caption' });
  const chartBox = h('div');
  const errImg = h('img', { id: 'error-map', class: 'errmap', alt: 'error map', hidden: true });
  const events = h('ol', { class: 'events', id: 'events' });
  const cancelBtn = h('button', { type: 'button', class: 'danger', id: 'cancel' }, 'Cancel');
  const pauseBtn = h('button', { type: 'button', id: 'pause' }, 'Pause');
  const priorityBtn = h('button', { type: 'button', id: 'priority' }, 'Priority');
  // A control's answer is the job's new status; a refusal (409: its state changed) is shown.
  const act = async (btn, url, opts) => {
    btn.disabled = true;
    try {
      st = await apiJson(url, opts);
      fetchedAt = performance.now();
      render();
    } catch (e) {
      alert(e.message);
    } finally {
      btn.disabled = false;
    }
  };
  pauseBtn.addEventListener('click', () => act(pauseBtn, `${path}/${st.state === 'paused' ? 'resume' : 'pause'}`, { method: 'POST' }));
  priorityBtn.addEventListener('click', () => {
    const v = prompt(`Priority of ${jobTitle(st)} (higher first):`, String(st.priority ?? 0));
    if (v === null) return;
    const n = Number(v.trim());
    if (!Number.isInteger(n)) {
      alert('The priority is a whole number.');
      return;
    }
    act(priorityBtn, path, { method: 'PATCH', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify({ priority: n }) });
  });
  const dl = (file, label) => h('button', {
    type: 'button',
    dataset: { file },
    onclick: (ev) => {
      const b = ev.currentTarget;
      b.disabled = true;
      download(`${path}/${file}`, `${st.name || st.id}-${file}`)
        .catch((e) => alert(`Download failed: ${e.message}`))
        .finally(() => { b.disabled = false; });
    },
  }, label);
  const dlExr = dl('image.exr', 'EXR');
  const dlPreview = dl('preview.png', 'Preview');
  const dlError = dl('error.png', 'Error map');
  const dlPlot = dl('convergence.svg', 'relMSE plot');
  cancelBtn.addEventListener('click', async () => {
    if (!confirm(`Cancel ${jobTitle(st)}?`)) return;
    cancelBtn.disabled = true;
    try {
      st = await apiJson(`${path}/cancel`, { method: 'POST' });
      fetchedAt = performance.now();
      render();
    } catch (e) {
      alert(e.message);
      cancelBtn.disabled = false;
    }
  });

  view().replaceChildren(
    h('div', { class: 'job-head' },
      h('h1', { id: 'job-title' }, jobTitle(st)), stateEl,
      h('span', { class: 'muted mono' }, st.id),
      h('div', { class: 'actions' }, pauseBtn, priorityBtn, cancelBtn, dlExr, dlPreview, dlError, dlPlot)),
    facts,
    strip,
    h('div', { class: 'panes' },
      h('figure', { class: 'panel' }, stage, caption),
      h('div', { class: 'side' },
        h('figure', { class: 'panel' }, h('h2', {}, 'relMSE against time'), chartBox),
        h('figure', { class: 'panel', id: 'error-pane' }, h('h2', {}, 'Error map'), errImg,
          h('figcaption', { class: 'hint' }, 'Red: brighter than the reference; green: darker. The bar under the map gives the relative error shown at full colour, fitted to this image.')),
        taskHistoryPanel(id, signal),
        h('details', { class: 'panel' }, h('summary', {}, 'Events'), events))));
  stage.style.aspectRatio = `${st.width} / ${st.height}`;

  function drawTiles() {
    const rect = stage.getBoundingClientRect();
    const dpr = window.devicePixelRatio || 1;
    canvas.width = Math.max(1, Math.round(rect.width * dpr));
    canvas.height = Math.max(1, Math.round(rect.height * dpr));
    const g = canvas.getContext('2d');
    g.clearRect(0, 0, canvas.width, canvas.height);
    if (!ACTIVE.has(st.state)) return;
    const sx = canvas.width / st.width;
    const sy = canvas.height / st.height;
    const size = (st.settings && st.settings.tile_size) || 32;
    const done = tilesDone.get(currentPass) || new Set();
    g.lineWidth = Math.max(1, dpr);
    for (let i = 0; i < st.tiles_per_pass; i++) {
      const [x0, y0, x1, y1] = tileRect(i, st.width, st.height, size);
      const [X, Y, Wd, Ht] = [x0 * sx, y0 * sy, (x1 - x0) * sx, (y1 - y0) * sy];
      if (done.has(i)) {
        g.fillStyle = 'rgba(120, 220, 150, 0.16)';
        g.fillRect(X, Y, Wd, Ht);
        g.strokeStyle = 'rgba(120, 230, 160, 0.95)';
      } else {
        g.strokeStyle = 'rgba(255, 255, 255, 0.18)';
      }
      g.strokeRect(X + 0.5, Y + 0.5, Wd - 1, Ht - 1);
    }
  }
  const resize = new ResizeObserver(() => drawTiles());
  resize.observe(stage);
  signal.addEventListener('abort', () => resize.disconnect());

  function fact(label, value, id) {
    return h('div', {}, h('dt', {}, label), h('dd', { id }, value));
  }

  function render() {
    const active = ACTIVE.has(st.state);
    const paused = st.state === 'paused';
    // Paused time is not rendering time: the clock stands still while paused.
    const elapsed = st.elapsed_s + (active && !paused && st.started_at ? (performance.now() - fetchedAt) / 1000 : 0);
    const eta = active && st.eta_s !== null ? Math.max(0, st.eta_s - (performance.now() - fetchedAt) / 1000) : null;
    const s = st.settings || {};
    stateEl.replaceChildren(stateBadge(st.state, 'job-state'));
    facts.replaceChildren(
      fact('Scene', st.scene.main),
      fact('Resolution', `${st.width} × ${st.height}`),
      fact('spp', sppText(st), 'job-spp'),
      fact('Passes', st.passes_total ? `${st.passes_done} / ${st.passes_total}` : st.passes_done),
      fact('Tiles this pass', active ? `${(tilesDone.get(currentPass) || new Set()).size} / ${st.tiles_per_pass}` : '—', 'job-tiles'),
      fact('Elapsed', fmtSeconds(elapsed), 'job-elapsed'),
      fact('ETA', paused ? 'paused' : active ? fmtSeconds(eta) : '—', 'job-eta'),
      fact('Priority', String(st.priority ?? 0), 'job-priority'),
      fact('relMSE', st.has_reference ? fmtRel(st.relmse) : 'no reference', 'job-relmse'),
      fact('Integrator', s.integrator === 'bdpt' ? `bdpt, ${s.mis}` : (s.integrator || '—')),
      ...(st.optimal_max_depth == null ? [] : [fact('Optimal max depth',
        st.optimal_depth ? `${st.optimal_max_depth} (auto: pilot ${st.optimal_depth.pilot_resolution.join(' × ')})` : `${st.optimal_max_depth}`, 'job-dopt')]),
      fact('Seed', s.seed ?? '—'));
    if (st.error) facts.append(h('div', { class: 'wide' }, h('dt', {}, 'Error'), h('dd', { class: 'error' }, st.error)));
    if (st.frames) {
      const shown = previewFrame();
      strip.hidden = false;
      strip.replaceChildren(h('span', { class: 'muted' }, 'Frames'), ...st.frames.map((f) => h('button', {
        type: 'button',
        class: `frame-chip state-${f.state}${f.frame === shown ? ' chosen' : ''}`,
        title: `frame ${f.frame}: ${f.state}, ${f.spp_done} spp${f.error ? ` (${f.error})` : ''} · job ${f.job_id}`,
        dataset: { frame: String(f.frame), job: f.job_id },
        onclick: () => {
          chosenFrame = f.frame;
          render();
          refreshImages();
        },
      }, String(f.frame))));
    }
    cancelBtn.hidden = !active;
    cancelBtn.disabled = false;
    pauseBtn.hidden = priorityBtn.hidden = !active;
    pauseBtn.textContent = paused ? 'Resume' : 'Pause';
    const any = st.passes_done > 0 || st.state === 'done';
    dlExr.disabled = dlPreview.disabled = !any;
    dlError.hidden = dlPlot.hidden = !st.has_reference;
    dlError.disabled = !any;
    document.getElementById('error-pane').hidden = !st.has_reference;
    const series = st.series || [];
    const key = `${st.has_reference}:${series.length}:${series.length ? series[series.length - 1].relmse : ''}`;
    if (key !== chartKey) {
      chartKey = key;
      chartBox.replaceChildren(st.has_reference
        ? relmseChart(series)
        : h('p', { class: 'muted' }, 'This job has no reference image, so no relMSE. Choose a reference (an EXR, or a finished job) when submitting.'));
    }
    caption.textContent = shownPass === null
      ? (active ? 'waiting for the first pass' : 'no preview')
      : `preview after pass ${shownPass + 1}${st.passes_total ? ` of ${st.passes_total}` : ''}` +
        (active ? ` · tiles of pass ${currentPass + 1} appear as they finish` : '');
    drawTiles();
  }

  // Images are fetched with the token, shown through object URLs; one fetch at a time.
  const refreshImages = coalesce(async () => {
    if (signal.aborted) return;
    const pass = previewPass;
    const frame = previewFrame();
    const blob = frame === null
      ? await apiBlob(`${path}/preview.png`, signal)
      : await apiBlob(`${path}/preview.png?frame=${frame}`, signal).catch(() => null);
    if (!blob) return;
    const url = URL.createObjectURL(blob);
    await new Promise((resolve) => {
      img.onload = img.onerror = resolve;
      img.src = url;
    });
    if (previewUrl) URL.revokeObjectURL(previewUrl);
    previewUrl = url;
    img.hidden = false;
    // Small renders are shown enlarged with their pixels visible, not blurred.
    const small = img.naturalWidth * 2 <= stage.clientWidth;
    img.classList.toggle('pixelated', small);
    errImg.classList.toggle('pixelated', small);
    img.dataset.pass = String(pass);
    placeholder.hidden = true;
    shownPass = Math.max(pass, 0);
    if (st.has_reference) {
      const eb = await apiBlob(`${path}/error.png`, signal).catch(() => null);
      if (eb) {
        const eu = URL.createObjectURL(eb);
        errImg.src = eu;
        errImg.hidden = false;
        if (errorUrl) URL.revokeObjectURL(errorUrl);
        errorUrl = eu;
      }
    }
    render();
  });

  const refreshStatus = coalesce(async () => {
    if (signal.aborted) return;
    st = await apiJson(path, { signal });
    fetchedAt = performance.now();
    currentPass = Math.max(currentPass, st.passes_done);
    render();
  });

  function logEvent(type, data, eventId) {
    const bits = [];
    if (data.pass !== undefined) bits.push(`pass ${data.pass}`);
    if (data.tile !== undefined) bits.push(`tile ${data.tile}`);
    if (data.spp !== undefined) bits.push(`${data.spp} spp`);
    if (data.relmse !== undefined && data.relmse !== null) bits.push(`relMSE ${fmtRel(data.relmse)}`);
    if (data.worker) bits.push(`worker ${short(data.worker)}`);
    if (data.error) bits.push(data.error);
    events.prepend(h('li', { dataset: { id: eventId || '' } }, h('span', { class: 'muted' }, fmtClock(data.at), ' '), h('span', { class: 'kind' }, type), bits.join(', ')));
    while (events.childElementCount > 200) events.lastElementChild.remove();
  }

  function onEvent(type, data, eventId) {
    logEvent(type, data, eventId);
    if (type === 'tile_done') {
      if (!tilesDone.has(data.pass)) tilesDone.set(data.pass, new Set());
      tilesDone.get(data.pass).add(data.tile);
      if (data.pass === currentPass) render();
    } else if (type === 'pass_done') {
      tilesDone.delete(data.pass);
      currentPass = Math.max(currentPass, data.pass + 1);
      st.passes_done = Math.max(st.passes_done, data.pass + 1);
      st.spp_done = Math.max(st.spp_done, data.spp);
      if (st.has_reference && data.relmse !== null) {
        st.series = (st.series || []).filter((p) => p.pass !== data.pass).concat([data]);
        st.relmse = data.relmse;
      }
      render();
      refreshStatus();
    } else if (type === 'preview') {
      previewPass = Math.max(previewPass, data.pass);
      refreshImages();
    } else if (TERMINAL.has(type) || type === 'task_failed') {
      refreshStatus();
      if (type === 'done') refreshImages();
    }
  }

  render();
  if (st.passes_done > 0) refreshImages();
  const tick = setInterval(() => {
    if (ACTIVE.has(st.state)) render();
  }, 1000);
  signal.addEventListener('abort', () => clearInterval(tick));
  if (ACTIVE.has(st.state)) {
    const live = document.getElementById('live');
    const isOver = async () => {
      await refreshStatus();
      return !ACTIVE.has(st.state);
    };
    followEvents(id, onEvent, (s) => { live.textContent = s === 'live' ? '● live' : 'reconnecting…'; }, isOver, signal)
      .then(() => refreshStatus())
      .catch((e) => { live.textContent = e.message; })
      .finally(() => { if (!signal.aborted) live.textContent = ''; });
  } else {
    // An ended job: its events once, for the log.
    followEvents(id, logEvent, () => {}, async () => true, signal).catch(() => {});
  }
}

// -- workers --

/** Buttons of an operator's controls of worker `w`: disable, enable, drain, clear unhealthy. */
function workerActions(w) {
  const base = `/v1/workers/${encodeURIComponent(w.id)}`;
  const act = (label, method, suffix) => {
    const b = h('button', { type: 'button', class: 'small', dataset: { action: suffix } }, label);
    b.addEventListener('click', async () => {
      b.disabled = true;
      try {
        await apiJson(`${base}/${suffix}`, { method });
        b.textContent = 'done';
      } catch (e) {
        alert(e.message);
        b.disabled = false;
      }
    });
    return b;
  };
  if (['left', 'gone'].includes(w.state)) return '';
  const admin = w.admin || 'enabled';
  return [
    admin === 'enabled' ? act('Disable', 'POST', 'disable') : act('Enable', 'POST', 'enable'),
    admin !== 'draining' ? act('Drain', 'POST', 'drain') : '',
    w.unhealthy ? act('Clear unhealthy', 'DELETE', 'unhealthy') : '',
  ];
}

async function workersView(signal) {
  document.title = 'omis: workers';
  const body = h('tbody');
  const history = new Map(); // worker id -> [[seconds, tasks_done]] of the last minute
  view().replaceChildren(
    h('div', { class: 'job-head' }, h('h1', {}, 'Workers')),
    h('table', { id: 'workers' },
      h('thead', {}, h('tr', {},
        h('th', {}, 'Worker'), h('th', {}, 'State'), h('th', { class: 'num' }, 'Threads'), h('th', {}, 'Current task'),
        h('th', { class: 'num' }, 'Tasks done'), h('th', { class: 'num' }, 'Tiles / min (last minute)'),
        h('th', { class: 'num' }, 'Tiles / min (overall)'), h('th', { class: 'num' }, 'Last seen'),
        h('th', {}, 'Tags'), h('th', {}, 'Admin'))),
      body),
    h('p', { class: 'hint' }, 'A task is one tile for one pass, or the merge of a finished pass into one band group of tiles. Workers that left (drained) or went silent past twice the lease time are listed dimmed. A worker that failed tasks of 3 jobs since its last result is unhealthy and gets no task (hover for why); one that failed 3 tasks of a job is kept from that job.'));
  await every(2000, signal, async () => {
    const { workers } = await apiJson('/v1/workers', { signal });
    const now = Date.now() / 1000;
    const order = { busy: 0, idle: 1, gone: 2, left: 3 };
    workers.sort((a, b) => (order[a.state] ?? 9) - (order[b.state] ?? 9) || a.name.localeCompare(b.name));
    if (!workers.length) {
      body.replaceChildren(h('tr', {}, h('td', { colspan: 10, class: 'empty' }, 'No worker has registered. Start one with omis worker --coordinator URL.')));
      return;
    }
    body.replaceChildren(...workers.map((w) => {
      const hist = (history.get(w.id) || []).filter(([t]) => now - t <= 60);
      hist.push([now, w.tasks_done]);
      history.set(w.id, hist);
      const [t0, n0] = hist[0];
      const recent = now - t0 >= 4 ? ((w.tasks_done - n0) / (now - t0)) * 60 : null;
      const life = Math.max(w.last_seen - w.registered_at, 1);
      const tasks = w.tasks || [];
      return h('tr', { class: ['left', 'gone'].includes(w.state) ? 'departed' : '' },
        h('td', {}, w.name, ' ', h('span', { class: 'muted mono' }, short(w.id))),
        h('td', {}, stateBadge(w.state),
          w.unhealthy ? [' ', h('span', { class: 'state state-failed', title: w.unhealthy }, 'unhealthy')] : '',
          (w.blocklisted_jobs || []).length
            ? [' ', h('span', { class: 'muted', title: w.blocklisted_jobs.join(', ') },
              `kept from ${w.blocklisted_jobs.length} job${w.blocklisted_jobs.length > 1 ? 's' : ''}`)]
            : ''),
        h('td', { class: 'num' }, w.threads),
        h('td', {}, tasks.length
          ? tasks.map((t, i) => [i ? ', ' : '', h('a', { href: `#/jobs/${t.job_id}` }, `job ${short(t.job_id)}`),
            t.kind === 'merge' ? ` merging pass ${t.pass} (band group ${t.tile})` : ` pass ${t.pass} tile ${t.tile}`])
          : h('span', { class: 'muted' }, '—')),
        h('td', { class: 'num' }, w.tasks_done),
        h('td', { class: 'num' }, recent === null ? '…' : recent.toFixed(1)),
        h('td', { class: 'num' }, ((w.tasks_done / life) * 60).toFixed(1)),
        h('td', { class: 'num' }, `${fmtSeconds(Math.max(0, now - w.last_seen))} ago`),
        h('td', { class: 'mono' }, (w.tags || []).join(', ') || '—'),
        h('td', {}, w.admin || 'enabled', ' ', workerActions(w)));
    }));
  });
}

// -- the job form --

/** A ustar archive of `files` ([name, Uint8Array]). */
function tarArchive(files) {
  const enc = new TextEncoder();
  const blocks = [];
  const put = (hdr, off, len, s) => hdr.set(enc.encode(s).subarray(0, len), off);
  const octal = (n, len) => n.toString(8).padStart(len - 1, '0') + '\0';
  for (const [name, data] of files) {
    const hdr = new Uint8Array(512);
    let nm = name;
    let prefix = '';
    if (enc.encode(nm).length > 100) {
      const cut = nm.lastIndexOf('/', 155);
      if (cut <= 0 || enc.encode(nm.slice(cut + 1)).length > 100) throw new Error(`${name}: path too long for a tar archive`);
      prefix = nm.slice(0, cut);
      nm = nm.slice(cut + 1);
    }
    put(hdr, 0, 100, nm);
    put(hdr, 100, 8, '0000644\0');
    put(hdr, 108, 8, '0000000\0');
    put(hdr, 116, 8, '0000000\0');
    put(hdr, 124, 12, octal(data.length, 12));
    put(hdr, 136, 12, octal(Math.floor(Date.now() / 1000), 12));
    put(hdr, 148, 8, '        ');
    put(hdr, 156, 1, '0');
    put(hdr, 257, 6, 'ustar\0');
    put(hdr, 263, 2, '00');
    put(hdr, 345, 155, prefix);
    const sum = hdr.reduce((a, b) => a + b, 0);
    put(hdr, 148, 8, sum.toString(8).padStart(6, '0') + '\0 ');
    blocks.push(hdr, data);
    const pad = (512 - (data.length % 512)) % 512;
    if (pad) blocks.push(new Uint8Array(pad));
  }
  blocks.push(new Uint8Array(1024));
  return new Blob(blocks, { type: 'application/x-tar' });
}

async function submitView(signal) {
  document.title = 'omis: new job';
  const opt = (v, label, selected) => h('option', { value: v, selected }, label || v);
  const num = (name, attrs = {}) => h('input', { type: 'number', name, id: `f-${name}`, ...attrs });
  const field = (label, input, hint) => h('label', {}, label, input, hint ? h('span', { class: 'hint' }, hint) : null);
  const library = h('select', { name: 'library', id: 'f-library' }, opt('', 'loading…'));
  const files = h('input', { type: 'file', name: 'files', id: 'f-files', multiple: true });
  const folder = h('input', { type: 'file', name: 'folder', id: 'f-folder', webkitdirectory: true });
  const main = h('input', { type: 'text', name: 'main', id: 'f-main', placeholder: 'scene.json' });
  const refJob = h('select', { name: 'refjob', id: 'f-refjob' }, opt('', 'loading…'));
  const refFile = h('input', { type: 'file', name: 'reffile', id: 'f-reffile', accept: '.exr' });
  const radio = (name, value, label, checked) =>
    h('label', { class: 'inline' }, h('input', { type: 'radio', name, value, checked, id: `f-${name}-${value}` }), label);
  const errorBox = h('div', { class: 'form-error', id: 'form-error', hidden: true });
  const submit = h('button', { type: 'submit', class: 'primary', id: 'f-submit' }, 'Submit job');

  const form = h('form', { class: 'job-form', id: 'job-form', novalidate: true },
    h('fieldset', {}, h('legend', {}, 'Scene'),
      h('div', { class: 'row' }, radio('source', 'library', 'From the library', true), library),
      h('div', { class: 'row spaced' }, radio('source', 'upload', 'Upload', false),
        field('A tar bundle, or a scene file with the meshes and textures it reads', files),
        field('… or a folder', folder),
        field('Main scene file (when several)', main)),
      h('p', { class: 'hint' }, 'Files are packed into one bundle (POST /v1/scenes) and paths stay relative to the scene file.')),
    h('fieldset', {}, h('legend', {}, 'Settings'),
      h('div', { class: 'row' },
        field('Name', h('input', { type: 'text', name: 'name', id: 'f-name', maxlength: 200 })),
        field('Width', num('width', { min: 1, placeholder: 'scene' })),
        field('Height', num('height', { min: 1, placeholder: 'scene' })),
        field('Samples per pixel', num('spp', { min: 1, placeholder: 'scene / 16' })),
        field('Time budget (s)', num('time_budget_s', { min: 0.1, step: 'any', placeholder: 'none' }))),
      h('div', { class: 'row spaced' },
        field('Integrator', h('select', { name: 'integrator', id: 'f-integrator' }, opt('pt', 'path tracer (pt)'), opt('bdpt', 'bidirectional (bdpt)'), opt('vcm', 'connection + merging (vcm)'), opt('bpm', 'photon mapping (bpm)'))),
        field('MIS (bdpt)', h('select', { name: 'mis', id: 'f-mis' }, opt('balance'), opt('power'), opt('optimal'), opt('optimal-progressive'))),
        field('Max depth', num('max_depth', { min: 0, placeholder: 'scene / 5' })),
        field('Seed', num('seed', { min: 0, value: 0 })),
        field('Pass size (spp)', num('pass_size', { min: 1, value: 16 })),
        field('Tile size (px)', num('tile_size', { min: 1, placeholder: 'auto' }))),
      h('details', { class: 'spaced' }, h('summary', {}, 'More settings'),
        h('div', { class: 'row spaced' },
          field('Sampler', h('select', { name: 'sampler', id: 'f-sampler' }, opt('sobol'), opt('stratified'), opt('independent'))),
          field('Direct light (pt)', h('select', { name: 'direct', id: 'f-direct' }, opt('mis'), opt('light'), opt('bsdf'))),
          field('Techniques (bdpt)', h('select', { name: 'techniques', id: 'f-techniques' }, opt('all'), opt('lt'), opt('nee'))),
          field('Optimal max depth', num('optimal_max_depth', { min: 0, placeholder: 'auto' })),
          field('kappa', num('kappa', { min: 0, step: 'any', placeholder: 'default' })),
          field('relMSE eps', num('eps', { min: 0, step: 'any', placeholder: '0.01' })),
          h('label', { class: 'inline' }, h('input', { type: 'checkbox', name: 'depth_layers', id: 'f-depth_layers' }), 'depth layers'),
          h('label', { class: 'inline' }, h('input', { type: 'checkbox', name: 'strategies', id: 'f-strategies' }), 'strategy layers (bdpt)')))),
    h('fieldset', {}, h('legend', {}, 'Reference (for relMSE and the error map)'),
      h('div', { class: 'row' }, radio('ref', 'none', 'None', true)),
      h('div', { class: 'row spaced' }, radio('ref', 'job', 'A finished job', false), refJob),
      h('div', { class: 'row spaced' }, radio('ref', 'upload', 'An EXR', false), refFile),
      h('p', { class: 'hint' }, 'The reference must have the resolution of this job.')),
    errorBox,
    h('div', {}, submit));
  view().replaceChildren(h('div', { class: 'job-head' }, h('h1', {}, 'New job')), form);

  const choose = (name, value) => () => { form.querySelector(`#f-${name}-${value}`).checked = true; };
  library.addEventListener('change', choose('source', 'library'));
  files.addEventListener('change', choose('source', 'upload'));
  folder.addEventListener('change', choose('source', 'upload'));
  refJob.addEventListener('change', choose('ref', 'job'));
  refFile.addEventListener('change', choose('ref', 'upload'));

  const [scenes, jobs] = await Promise.all([
    apiJson('/v1/scenes', { signal }).catch((e) => ({ library: [], error: e })),
    allJobs({ signal }, 'state=done').catch(() => ({ jobs: [] })),
  ]);
  library.replaceChildren(...(scenes.library.length
    ? scenes.library.map((n) => opt(n, n, n === 'cornell-box'))
    : [opt('', scenes.error ? scenes.error.message : 'no library on this server')]));
  const done = jobs.jobs.filter((j) => j.state === 'done').sort((a, b) => b.created_at - a.created_at);
  refJob.replaceChildren(...(done.length
    ? done.map((j) => opt(j.id, `${jobTitle(j)} · ${j.scene.main} · ${j.width}×${j.height} · ${j.spp_done} spp`))
    : [opt('', 'no finished job')]));

  form.addEventListener('submit', async (ev) => {
    ev.preventDefault();
    errorBox.hidden = true;
    form.querySelectorAll('.invalid').forEach((el) => el.classList.remove('invalid'));
    submit.disabled = true;
    const fail = (msg, field) => {
      errorBox.textContent = msg;
      errorBox.hidden = false;
      const name = field && field.replace(/^settings\./, '').replace(/^scene\..*/, 'library').replace(/^reference\..*/, 'refjob');
      const el = name && (form.querySelector(`#f-${name}`) || (name === 'resolution' && form.querySelector('#f-width')));
      if (el) el.classList.add('invalid');
      submit.disabled = false;
    };
    try {
      const fd = new FormData(form);
      const val = (k) => String(fd.get(k) ?? '').trim();
      const int = (k) => (val(k) === '' ? undefined : Number(val(k)));
      const settings = {
        integrator: val('integrator'), mis: val('mis'), sampler: val('sampler'),
        direct: val('direct'), techniques: val('techniques'),
        seed: int('seed') ?? 0, pass_size: int('pass_size') ?? 16,
        depth_layers: fd.get('depth_layers') !== null, strategies: fd.get('strategies') !== null,
      };
      for (const k of ['spp', 'time_budget_s', 'max_depth', 'optimal_max_depth', 'kappa', 'eps', 'tile_size']) {
        if (int(k) !== undefined) settings[k] = int(k);
      }
      if (int('width') !== undefined || int('height') !== undefined) {
        if (int('width') === undefined || int('height') === undefined) return fail('Give both width and height, or neither.', 'width');
        settings.resolution = [int('width'), int('height')];
      }
      const req = { settings };
      if (val('name')) req.name = val('name');
      submit.textContent = 'Submitting…';
      if (val('source') === 'upload') {
        const picked = [...files.files].map((f) => [f.name, f]);
        const tree = [...folder.files].map((f) => [f.webkitRelativePath.split('/').slice(1).join('/') || f.name, f]);
        const all = picked.concat(tree);
        if (!all.length) return fail('Choose a scene file, bundle or folder to upload.', 'files');
        let body;
        if (all.length === 1 && /\.tar$/i.test(all[0][0])) {
          body = all[0][1];
        } else {
          body = tarArchive(await Promise.all(all.map(async ([n, f]) => [n, new Uint8Array(await f.arrayBuffer())])));
        }
        const q = val('main') ? `?main=${encodeURIComponent(val('main'))}` : '';
        const meta = await apiJson(`/v1/scenes${q}`, { method: 'POST', headers: { 'Content-Type': 'application/x-tar' }, body });
        req.scene = { bundle: meta.id };
      } else {
        if (!val('library')) return fail('Choose a library scene.', 'library');
        req.scene = { library: val('library') };
      }
      if (val('ref') === 'job') {
        if (!val('refjob')) return fail('Choose a finished job as the reference.', 'refjob');
        req.reference = { job: val('refjob') };
      } else if (val('ref') === 'upload') {
        const f = refFile.files[0];
        if (!f) return fail('Choose an EXR file as the reference.', 'reffile');
        const r = await apiJson('/v1/references', { method: 'POST', headers: { 'Content-Type': 'image/x-exr' }, body: f });
        req.reference = { upload: r.id };
      }
      const st = await apiJson('/v1/jobs', {
        method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(req),
      });
      location.hash = `#/jobs/${st.id}`;
    } catch (e) {
      fail(e.message, e.field);
    } finally {
      submit.textContent = 'Submit job';
    }
  });
}

// ---- routing ----

let current = null;

async function route() {
  if (current) current.abort();
  current = new AbortController();
  const { signal } = current;
  document.getElementById('live').textContent = '';
  const parts = (location.hash.replace(/^#\/?/, '') || 'jobs').split('/');
  document.querySelectorAll('header nav a').forEach((a) => {
    a.classList.toggle('active', a.dataset.nav === parts[0]);
  });
  try {
    if (parts[0] === 'jobs' && parts[1]) await jobView(signal, decodeURIComponent(parts[1]));
    else if (parts[0] === 'workers') await workersView(signal);
    else if (parts[0] === 'submit') await submitView(signal);
    else await jobsView(signal);
  } catch (e) {
    if (!signal.aborted) showError(e);
  }
}

document.addEventListener('DOMContentLoaded', () => {
  document.getElementById('forget').addEventListener('click', () => {
    sessionStorage.removeItem(TOKEN_KEY);
    updateTokenButton();
    route();
  });
  // Escape would leave every waiting call waiting: the dialog stays until a token is given.
  document.getElementById('token-dialog').addEventListener('cancel', (ev) => ev.preventDefault());
  updateTokenButton();
  window.addEventListener('hashchange', route);
  route();
});
