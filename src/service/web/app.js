// The ptv lab page: calibrations, sequences with live progress, a frame
// viewer and a 3D view of a frame's particles. Plain JavaScript, no
// library, no build step; it reads the service's own API (/api/v1) and
// nothing else.
'use strict';

(() => {
  const API = '/api/v1';
  const TOKEN_KEY = 'ptv-api-token';
  const main = document.getElementById('main');
  /** Functions to call when the view changes (streams, listeners). */
  let cleanups = [];

  // ---- Errors: every window error, unhandled rejection and console.error
  // is shown and counted (#error-count), so nothing fails silently.
  let errorCount = 0;
  function reportError(message) {
    errorCount += 1;
    document.getElementById('error-count').textContent = String(errorCount);
    document.getElementById('error-badge').classList.add('bad');
    const list = document.getElementById('errors');
    list.hidden = false;
    list.append(el('li', { text: message }));
  }
  window.addEventListener('error', (e) => reportError(`error: ${e.message}`));
  window.addEventListener('unhandledrejection', (e) => {
    const reason = e.reason;
    if (reason instanceof NeedToken) return;
    reportError(`unhandled: ${reason && reason.message ? reason.message : String(reason)}`);
  });
  const consoleError = console.error.bind(console);
  console.error = (...args) => {
    reportError(args.map(String).join(' '));
    consoleError(...args);
  };

  // ---- DOM helpers.
  function el(tag, props = {}, ...children) {
    const node = document.createElement(tag);
    for (const [key, value] of Object.entries(props)) {
      if (value === undefined || value === null) continue;
      if (key === 'text') node.textContent = value;
      else if (key === 'class') node.className = value;
      else if (key.startsWith('on')) node.addEventListener(key.slice(2), value);
      else if (key === 'dataset') Object.assign(node.dataset, value);
      else node.setAttribute(key, value);
    }
    for (const child of children.flat()) {
      if (child === null || child === undefined || child === false) continue;
      node.append(child instanceof Node ? child : String(child));
    }
    return node;
  }
  function table(headers, rows, numeric = []) {
    return el('table', {},
      el('thead', {}, el('tr', {}, headers.map((h, i) =>
        el('th', { class: numeric.includes(i) ? 'num' : undefined, text: h })))),
      el('tbody', {}, rows.map((cells) => el('tr', {}, cells.map((c, i) =>
        el('td', { class: numeric.includes(i) ? 'num' : undefined }, c))))));
  }
  function fmt(value, digits = 6) {
    if (value === null || value === undefined) return '–';
    if (typeof value !== 'number') return String(value);
    if (value === 0) return '0';
    const magnitude = Math.abs(value);
    if (magnitude >= 1e5 || magnitude < 1e-3) return value.toExponential(digits - 2);
    return String(Number(value.toPrecision(digits)));
  }
  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

  // ---- The API, with the token of this tab (sessionStorage) if the
  // service asks for one.
  class NeedToken extends Error {}
  class HttpError extends Error {
    constructor(status, detail) {
      super(`${status}: ${detail}`);
      this.status = status;
      this.detail = detail;
    }
  }
  function headers(extra = {}) {
    const result = { ...extra };
    const token = sessionStorage.getItem(TOKEN_KEY);
    if (token) result.Authorization = `Bearer ${token}`;
    return result;
  }
  /** fetch, waiting and trying again (at most 5 times) when the service
   * sheds the request: a 503 with Retry-After means it is busy with as
   * many CPU-heavy requests (plots, projections) as it runs at once. */
  async function send(url, options = {}) {
    for (let attempt = 1; ; attempt += 1) {
      const response = await fetch(url, options);
      const retry = response.headers.get('Retry-After');
      if (response.status !== 503 || retry === null || attempt > 5) return response;
      await sleep(Math.min(Number(retry) || 1, 10) * 1000);
    }
  }
  /** Images (plots, overlays) are drawn on the service's CPU threads: the
   * page asks for one at a time, so that it is not shed. */
  let imageQueue = Promise.resolve();
  function oneAtATime(task) {
    const run = imageQueue.then(task, task);
    imageQueue = run.catch(() => {});
    return run;
  }
  async function api(path, options = {}) {
    const response = await send(API + path, { ...options, headers: headers(options.headers) });
    if (response.status === 401) {
      let detail = '';
      try { detail = (await response.json()).detail || ''; } catch (_) { /* not JSON */ }
      askToken(sessionStorage.getItem(TOKEN_KEY) !== null, detail);
      throw new NeedToken('the API token is needed');
    }
    if (!response.ok) {
      let detail = response.statusText;
      try { detail = (await response.json()).detail || detail; } catch (_) { /* not JSON */ }
      throw new HttpError(response.status, detail);
    }
    return response;
  }
  const getJson = async (path) => (await api(path)).json();
  const postJson = async (path, body) => (await api(path, {
    method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
  })).json();

  /** Shows the token form; after a token was tried (`wrong`), says that
   * the service refused it, with the service's words (kept until another
   * token is given). */
  function askToken(wrong, detail) {
    const form = document.getElementById('token-form');
    form.hidden = false;
    const said = document.getElementById('token-error');
    if (wrong) {
      sessionStorage.removeItem(TOKEN_KEY);
      showForget();
      said.textContent = `The service did not accept that token (HTTP 401${detail ? `: ${detail}` : ''}). `
        + 'Give the token the service was started with (--api-token).';
      said.hidden = false;
    }
    document.getElementById('token-input').focus();
  }
  document.getElementById('token-form').addEventListener('submit', (e) => {
    e.preventDefault();
    const input = document.getElementById('token-input');
    sessionStorage.setItem(TOKEN_KEY, input.value.trim());
    input.value = '';
    // A new token: what was said of the last one goes (it is said again
    // if this one is refused too; the view's parallel requests all come
    // back 401, and only the first finds the token to forget).
    document.getElementById('token-error').hidden = true;
    e.target.hidden = true;
    showForget();
    route();
  });
  function showForget() {
    document.getElementById('forget-token').hidden = sessionStorage.getItem(TOKEN_KEY) === null;
  }
  document.getElementById('forget-token').addEventListener('click', () => {
    sessionStorage.removeItem(TOKEN_KEY);
    showForget();
    route();
  });

  // ---- Plots: fetched with the token and shown from a blob; a plot the
  // service cannot give (not there, or no image kept) says so instead.
  // A plot is shown as wide as the page allows (at most its own size);
  // a click on it shows it at full size (scrolling), and its link opens
  // the picture alone. `figure.release()` frees its image (a plot that
  // is drawn again).
  function plot(path, caption) {
    const figure = el('figure', { class: 'plot', dataset: { src: API + path, loaded: 'pending' } });
    let url = null;
    const release = () => { if (url) URL.revokeObjectURL(url); url = null; };
    figure.release = release;
    cleanups.push(release);
    figure.ready = (async () => {
      try {
        const response = await oneAtATime(() => send(API + path, { headers: headers() }));
        if (!response.ok) throw new HttpError(response.status, response.statusText);
        const image = el('img', { alt: caption, title: 'click: full size / fit' });
        url = URL.createObjectURL(await response.blob());
        image.src = url;
        await image.decode();
        image.addEventListener('click', () => figure.classList.toggle('full'));
        figure.replaceChildren(el('div', { class: 'frame' }, image), el('figcaption', {}, caption,
          ` (${image.naturalWidth}×${image.naturalHeight} px; click for full size or `,
          el('a', { href: url, target: '_blank', rel: 'noopener', class: 'open', text: 'open it alone' }), ')'));
        figure.dataset.loaded = 'yes';
      } catch (error) {
        const why = error instanceof HttpError ? `HTTP ${error.status}` : 'it does not load';
        figure.replaceChildren(el('p', { class: 'noplot', text: `no plot: ${caption} (${why})` }));
        figure.dataset.loaded = 'no';
      }
    })();
    return figure;
  }

  // ---- Server-sent events read with fetch (EventSource cannot send the
  // Authorization header); reconnects after a pause, each time from a
  // fresh snapshot.
  function follow(path, onEvent, onStatus) {
    const controller = new AbortController();
    let stopped = false;
    (async () => {
      while (!stopped) {
        try {
          onStatus('connecting');
          const response = await api(path, { headers: { Accept: 'text/event-stream' }, signal: controller.signal });
          onStatus('live');
          const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
          let buffer = '';
          for (;;) {
            const { value, done } = await reader.read();
            if (done) break;
            buffer += value.replace(/\r\n?/g, '\n');
            let end;
            while ((end = buffer.indexOf('\n\n')) >= 0) {
              const block = buffer.slice(0, end);
              buffer = buffer.slice(end + 2);
              let name = 'message';
              const data = [];
              for (const line of block.split('\n')) {
                if (line.startsWith('event:')) name = line.slice(6).trim();
                else if (line.startsWith('data:')) data.push(line.slice(5).replace(/^ /, ''));
              }
              if (data.length) onEvent(name, JSON.parse(data.join('\n')));
            }
          }
        } catch (error) {
          if (stopped || error instanceof NeedToken) return;
          if (error instanceof HttpError && error.status === 404) { onStatus('gone'); return; }
        }
        if (stopped) return;
        onStatus('reconnecting');
        await sleep(2000);
      }
    })();
    return () => { stopped = true; controller.abort(); };
  }

  // ---- Views.
  async function home() {
    main.replaceChildren(el('h1', { text: 'Calibrations and sequences' }));
    const calibrations = el('section', { id: 'calibrations' }, el('h2', { text: 'Calibrations' }));
    const sequences = el('section', { id: 'sequences' }, el('h2', { text: 'Sequences' }));
    main.append(calibrations, sequences);
    await Promise.all([
      pages(calibrations, '/calibrations', ['id', 'cameras', 'report', 'refined from', 'stored'], (c) => [
        el('a', { href: `#/calibrations/${c.id}`, text: `calibration ${c.id}` }), c.cameras,
        c.has_report ? 'yes' : 'no',
        c.origin_calibration ? el('a', { href: `#/calibrations/${c.origin_calibration}`, text: String(c.origin_calibration) }) : '–',
        c.created_at], [1]),
      pages(sequences, '/sequences', ['id', 'name', 'calibration', 'queued', 'running', 'done', 'failed', 'created'], (s) => [
        el('a', { href: `#/sequences/${s.id}`, text: `sequence ${s.id}` }), s.name || '–',
        el('a', { href: `#/calibrations/${s.calibration_id}`, text: String(s.calibration_id) }),
        s.frames.queued, s.frames.running, s.frames.done, s.frames.failed, s.created_at], [3, 4, 5, 6]),
    ]);
  }

  /** A list with a "more" button that follows `next`. */
  async function pages(section, path, headings, row, numeric) {
    const body = await getJson(path);
    if (!body.items.length) {
      section.append(el('p', { class: 'note', text: 'None yet.' }));
      return;
    }
    const list = table(headings, body.items.map(row), numeric);
    section.append(list);
    let next = body.next;
    if (next) {
      const more = el('button', { type: 'button', text: 'more' });
      more.addEventListener('click', async () => {
        const page = await getJson(next.replace(API, ''));
        const rows = table(headings, page.items.map(row), numeric).querySelector('tbody').children;
        list.querySelector('tbody').append(...rows);
        next = page.next;
        if (!next) more.remove();
      });
      section.append(more);
    }
  }

  async function calibrationPage(id) {
    const calibration = await getJson(`/calibrations/${id}`);
    const report = calibration.report;
    main.replaceChildren(el('h1', { text: `Calibration ${id}: ${calibration.cameras} cameras` }),
      el('p', { class: 'note' }, `Stored ${calibration.created_at}`,
        calibration.origin_calibration ? ['; refined from ', el('a', { href: `#/calibrations/${calibration.origin_calibration}`, text: `calibration ${calibration.origin_calibration}` })] : '',
        '. Files: ', el('a', { href: `${API}/calibrations/${id}`, text: 'JSON' })));
    if (report && report.check_points) {
      const c = report.check_points;
      main.append(el('h2', { text: 'Check points' }), el('div', { class: 'cards', id: 'check-points' },
        card('check points', c.count, 'check-count'),
        card('RMSE (mm)', fmt(c.rmse_mm, 4), 'check-rmse'),
        card('RMSE x, y, z (mm)', `${fmt(c.rmse_x_mm, 3)}, ${fmt(c.rmse_y_mm, 3)}, ${fmt(c.rmse_z_mm, 3)}`),
        card('relative accuracy', `1:${Math.round(c.relative_accuracy)}`)));
    }
    if (report && report.outcome) {
      main.append(el('h2', { text: 'Self-calibration' }), el('div', { class: 'cards' },
        card('outcome', report.outcome), card('σ₀ (px)', report.sigma0_px.toFixed(4), 'selfcal-sigma0'),
        card('frames', report.frames)),
      plot(`/calibrations/${id}/disparity.png`, 'disparity maps before and after'));
    }
    const models = calibration.model.cameras;
    models.forEach((model, c) => {
      const camera = report && report.cameras ? report.cameras[c] : null;
      const section = el('section', { class: 'camera', id: `camera-${c}` }, el('h2', { text: `Camera ${c}${model.name ? ` (${model.name})` : ''}` }));
      if (camera && camera.sigma0_px !== undefined) {
        section.append(el('div', { class: 'cards' },
          card('σ₀ (px)', camera.sigma0_px.toFixed(4), `sigma0-${c}`),
          card('points used', camera.points_used), card('redundancy', camera.redundancy),
          card('iterations', camera.iterations)));
      }
      if (camera && camera.parameters && camera.parameters.length) {
        section.append(parameterTable(camera.parameters));
      } else {
        section.append(table(['parameter', 'value'], Object.entries(model)
          .filter(([key]) => key !== 'media')
          .map(([key, value]) => [key, Array.isArray(value) ? value.map((v) => fmt(v)).join(', ') : fmt(value)])));
      }
      // Residual pictures exist for a report solved from control points
      // that says where each point was measured; a self-calibration's
      // report has disparities instead (its plot is above).
      if (camera && hasResiduals(report, camera)) {
        section.append(plot(`/calibrations/${id}/residuals.png?camera=${c}`, `residuals of camera ${c}`));
      } else if (camera && !report.outcome) {
        section.append(el('p', { class: 'note', text: 'No residual picture: this report was written before reports said where each point was measured (calibrate again to draw it).' }));
      }
      main.append(section);
    });
    if (!report) main.append(el('p', { class: 'note', text: 'No report: this calibration was stored as given, not solved.' }));
  }

  /** Whether the service can draw a camera's residuals: a solve's report
   * (not a self-calibration's) whose points say where they were measured. */
  function hasResiduals(report, camera) {
    if (report.outcome !== undefined || !Array.isArray(camera.residuals)) return false;
    return camera.residuals.concat(camera.excluded || []).every((r) => Array.isArray(r.image_px));
  }

  function card(label, value, id) {
    return el('div', { class: 'card' }, el('div', { class: 'value', id, text: String(value) }), el('div', { class: 'label', text: label }));
  }

  /** Parameters with sigmas; other columns (a self-calibration's) as given. */
  function parameterTable(parameters) {
    // The service's JSON comes with sorted keys: name, the values (a
    // self-calibration's before and after) and sigma first, then the rest
    // in the order found.
    const keys = ['name', 'value', 'before', 'after', 'change', 'sigma', 'status']
      .filter((k) => parameters.some((p) => k in p));
    for (const p of parameters) for (const k of Object.keys(p)) if (!keys.includes(k)) keys.push(k);
    const numeric = keys.map((k, i) => (parameters.some((p) => typeof p[k] === 'number') ? i : -1));
    return table(keys, parameters.map((p) => keys.map((k) => fmt(p[k]))), numeric);
  }

  async function sequencePage(id) {
    const sequence = await getJson(`/sequences/${id}`);
    const counts = el('div', { class: 'cards', id: 'counts' });
    const live = el('span', { class: 'live', id: 'live', text: 'connecting' });
    const throughput = el('span', { id: 'throughput', text: '–' });
    const log = el('ul', { id: 'events' });
    const frames = el('section', { id: 'frames' });
    main.replaceChildren(
      el('h1', { text: `Sequence ${id}${sequence.name ? `: ${sequence.name}` : ''}` }),
      el('p', { class: 'note' }, 'Calibration ', el('a', { href: `#/calibrations/${sequence.calibration_id}`, text: String(sequence.calibration_id) }),
        `; created ${sequence.created_at}; images ${sequence.keep_images ? 'kept' : 'not kept'}; background ${sequence.background}.`),
      el('h2', {}, 'Frames by state ', live), counts,
      el('p', {}, 'Throughput: ', throughput),
      el('details', {}, el('summary', { text: 'parameters' }), el('pre', { text: JSON.stringify(sequence.parameters, null, 2) })),
      el('h2', { text: 'Events' }), log, frames);
    showCounts(counts, sequence.frames);
    const tracking = trackingSection(id);
    main.append(tracking.node);
    tracking.update(sequence.tracking);
    cleanups.push(tracking.stop);
    const health = healthSection(id);
    main.append(health.node);
    await health.update();
    await showFrames(frames, id);

    // Throughput from the frames processed while this page is open.
    const processed = [];
    let refresh = null;
    const update = () => {
      if (refresh) return;
      refresh = setTimeout(async () => {
        refresh = null;
        try {
          const fresh = await getJson(`/sequences/${id}`);
          showCounts(counts, fresh.frames);
          tracking.update(fresh.tracking);
          await health.update();
          await showFrames(frames, id);
        } catch (error) {
          if (!(error instanceof NeedToken)) throw error;
        }
      }, 300);
    };
    const stop = follow(`/sequences/${id}/events`, (name, data) => {
      if (name === 'snapshot') { showCounts(counts, data.frames); return; }
      const line = name === 'lagged' ? `lagged: ${data.missed} events missed; re-read`
        : `${name}${data.frame !== undefined ? ` frame ${data.frame}` : ''}${data.state ? ` ${data.kind} ${data.state}` : ''}${data.tracked_through !== undefined ? ` through ${data.tracked_through}` : ''}`;
      log.prepend(el('li', { text: `${new Date().toLocaleTimeString()} ${line}` }));
      while (log.children.length > 50) log.lastChild.remove();
      if (name === 'frame_processed') {
        const now = performance.now();
        processed.push(now);
        while (processed.length && now - processed[0] > 60000) processed.shift();
        throughput.textContent = throughputText(processed, now);
      }
      update();
    }, (status) => {
      live.textContent = status;
      live.className = `live ${status === 'live' ? 'on' : status === 'connecting' ? '' : 'off'}`;
    });
    cleanups.push(stop, () => clearTimeout(refresh));
  }

  /** The rate of frames processed (`times`, ms, the last minute's) as
   * said on the page: a rate only once the frames span a second or more
   * (a rate over a few milliseconds says nothing), the span to a tenth of
   * a second below ten seconds. */
  function throughputText(times, now) {
    const n = times.length;
    const span = n > 1 ? (now - times[0]) / 1000 : 0;
    const frames = `${n} frame${n === 1 ? '' : 's'}`;
    if (span < 1) return `${frames} processed in the last ${span > 0 ? `${span.toFixed(1)} s` : 'moment'}`;
    const shown = span < 10 ? span.toFixed(1) : String(Math.round(span));
    return `${((n - 1) / span).toFixed(2)} frames/s over the last ${shown} s (${frames})`;
  }

  /** A sequence's tracking: its run's line and trajectories plot, drawn
   * again as the run goes on (the plot at most every PLOT_REFRESH_MS, and
   * once more when the run ends), hidden while there is no run. */
  const PLOT_REFRESH_MS = 4000;
  function trackingSection(id) {
    const line = el('p', { class: 'note', id: 'tracking-line' });
    const holder = el('div', { id: 'trajectories' });
    const node = el('section', { id: 'tracking', hidden: '' }, el('h2', { text: 'Trajectories' }), line, holder);
    let drawn = null;
    let wanted = null;
    let last = -Infinity;
    let timer = null;
    function redraw() {
      clearTimeout(timer);
      timer = null;
      last = performance.now();
      drawn = wanted;
      // The new picture replaces the old one once it is loaded (no blank
      // between the two).
      const figure = plot(`/sequences/${id}/trajectories.png`, 'trajectories coloured by speed');
      figure.dataset.key = drawn;
      const old = [...holder.children];
      figure.hidden = old.length > 0;
      holder.append(figure);
      figure.ready.then(() => {
        for (const o of old) { if (o.release) o.release(); o.remove(); }
        figure.hidden = false;
      });
    }
    return {
      node,
      update(run) {
        if (!run) { node.hidden = true; return; }
        node.hidden = false;
        line.textContent = `Tracking run ${run.run_id}: ${run.state}, tracked through frame ${run.tracked_through ?? '–'}.`;
        line.dataset.key = `${run.run_id} ${run.state} ${run.tracked_through ?? ''}`;
        wanted = line.dataset.key;
        if (wanted === drawn) return;
        const wait = PLOT_REFRESH_MS - (performance.now() - last);
        if (wait <= 0 || run.state !== 'tracking') redraw();
        else if (!timer) timer = setTimeout(redraw, wait);
      },
      stop() { clearTimeout(timer); },
    };
  }

  /** A sequence's calibration health: each camera's drift from the run's
   * first frames, and, once a camera's alarm fired, the advice to
   * self-calibrate; the plot over frames drawn again when an alarm fires
   * and every window of frames. */
  function healthSection(id) {
    const line = el('p', { class: 'note', id: 'health-line' });
    const advice = el('p', { class: 'warning', id: 'health-advice', hidden: '' });
    const holder = el('div', { id: 'health-plot' });
    const node = el('section', { id: 'health' }, el('h2', { text: 'Calibration health' }), line, advice, holder);
    let drawn = null;
    return {
      node,
      async update() {
        const h = await getJson(`/sequences/${id}/calibration-health`);
        const based = h.cameras.some((c) => c.baseline_px);
        line.textContent = h.through_frame === null ? 'No frame measured yet.'
          : !based ? `Through frame ${h.through_frame} (${h.frames} frames); the drift is watched once the first ${h.window} frames are measured.`
            : `Through frame ${h.through_frame} (${h.frames} frames); drift from the first ${h.window} frames: `
              + h.cameras.map((c) => `camera ${c.camera} ${c.drift_px.toFixed(3)} px`).join(', ')
              + ` (alarm above ${h.threshold_px} px).`;
        advice.hidden = !h.alarm;
        advice.textContent = h.advice || '';
        // Drawn again when an alarm fires and every window of frames.
        const key = `${h.calibration_id} ${h.alarm} ${Math.ceil(h.frames / h.window)}`;
        if (key === drawn || h.frames === 0) return;
        drawn = key;
        for (const o of [...holder.children]) { if (o.release) o.release(); o.remove(); }
        holder.append(plot(`/sequences/${id}/calibration-health.png`, 'each camera\'s mean disparity drift over frames'));
      },
    };
  }

  function showCounts(node, frames) {
    node.replaceChildren(...['queued', 'running', 'done', 'failed'].map((state) =>
      card(state, frames[state], `count-${state}`)));
  }

  async function showFrames(section, id) {
    const body = await getJson(`/sequences/${id}/frames?limit=1000`);
    const rows = body.items.map((f) => [
      el('a', { href: `#/sequences/${id}/frames/${f.frame}`, text: `frame ${f.frame}` }),
      el('span', { class: `state-${f.state}`, text: f.state }), f.particles ?? '–']);
    section.replaceChildren(el('h2', { text: 'Frames' }),
      rows.length ? table(['frame', 'state', 'particles'], rows, [2]) : el('p', { class: 'note', text: 'No frames yet.' }),
      body.next ? el('p', { class: 'note', text: 'The first 1000 frames; the rest through the API.' }) : '');
  }

  async function framePage(id, frame) {
    const sequence = await getJson(`/sequences/${id}`);
    main.replaceChildren(el('h1', {}, el('a', { href: `#/sequences/${id}`, text: `Sequence ${id}` }), ` · frame ${frame}`));
    let particles;
    try {
      particles = await getJson(`/sequences/${id}/frames/${frame}/particles`);
    } catch (error) {
      if (error instanceof HttpError && (error.status === 409 || error.status === 404)) {
        main.append(el('p', { class: 'problem', text: error.detail }));
        return;
      }
      throw error;
    }
    const calibration = await getJson(`/calibrations/${particles.calibration_id}`);
    const cameras = calibration.model.cameras;
    const points = particles.particles;
    main.append(el('div', { class: 'cards' },
      card('particles', points.length, 'particle-count'),
      card('cameras', cameras.length),
      card('made with calibration', particles.calibration_id)));

    // Reprojections of the particles into every camera, in one request.
    const projected = points.length
      ? (await postJson(`/calibrations/${particles.calibration_id}/project`, { points: points.map((p) => [p.x, p.y, p.z]) })).pixels
      : [];
    const viewer = frameViewer(id, frame, cameras, points, projected, sequence.keep_images);
    const view3d = particleView(points);
    main.append(el('div', { class: 'views' }, viewer.node, view3d.node),
      el('h2', { text: 'Plots' }), plot(`/sequences/${id}/frames/${frame}/particles.png`, 'three views of the particles'));
    await viewer.show(0);
    if (sequence.tracking) {
      try {
        const low = Math.max(0, frame - 10);
        const tracks = await getJson(`/sequences/${id}/trajectories?frames=${low}..${frame + 10}`);
        view3d.setTrajectories(tracks.trajectories);
      } catch (error) {
        if (!(error instanceof HttpError)) throw error;
      }
    }
  }

  /** A camera's image with its targets and the particles' reprojections,
   * with zoom (wheel, buttons), pan (drag) and a camera switch. */
  function frameViewer(id, frame, cameras, points, projected, keptImages) {
    const canvas = el('canvas', { id: 'frame-canvas', width: 640, height: 512 });
    const context = canvas.getContext('2d');
    const info = el('span', { class: 'note' });
    const buttons = cameras.map((_, c) => el('button', { type: 'button', id: `camera-button-${c}`, text: `camera ${c}` }));
    const zoomLabel = el('span', { id: 'zoom', text: '100%' });
    const marks = el('input', { type: 'checkbox', id: 'marks', checked: '' });
    marks.addEventListener('change', () => draw());
    // The camera's plain kept image (image.png) under the page's own
    // marks: one set of marks, explained by the one legend below.
    const imageNote = el('p', { class: 'note', id: 'image-note' });
    const node = el('section', { class: 'frame-viewer' },
      el('div', { class: 'toolbar' }, buttons,
        el('button', { type: 'button', text: '+', onclick: () => zoomAt(1.5, canvas.width / 2, canvas.height / 2) }),
        el('button', { type: 'button', text: '−', onclick: () => zoomAt(1 / 1.5, canvas.width / 2, canvas.height / 2) }),
        el('button', { type: 'button', text: 'fit', onclick: () => { fit(); draw(); } }), zoomLabel,
        el('label', {}, marks, ' marks')),
      canvas,
      el('p', { class: 'legend' }, el('span', {}, el('i', { class: 'swatch sw-used' }), 'target of a particle'),
        el('span', {}, el('i', { class: 'swatch sw-unused' }), 'unmatched target'),
        el('span', {}, el('i', { class: 'swatch sw-reproj' }), 'particle reprojected')),
      el('p', {}, 'Targets: ', el('b', { id: 'target-count', text: '–' }), ', used by particles: ', el('b', { id: 'used-count', text: '–' }),
        ', particles reprojected: ', el('b', { id: 'reprojected-count', text: '–' }), ' ', info), imageNote);
    const state = { camera: 0, targets: [], used: new Set(), image: null, scale: 1, x: 0, y: 0, zoom: 1 };
    const size = () => cameras[state.camera].image_size;

    function fit() {
      const [w, h] = size();
      state.scale = Math.min(canvas.width / w, canvas.height / h);
      state.zoom = 1;
      state.x = (canvas.width - w * state.scale) / 2;
      state.y = (canvas.height - h * state.scale) / 2;
    }
    function zoomAt(factor, cx, cy) {
      const next = Math.min(64, Math.max(0.25, state.zoom * factor));
      const applied = next / state.zoom;
      state.x = cx - (cx - state.x) * applied;
      state.y = cy - (cy - state.y) * applied;
      state.scale *= applied;
      state.zoom = next;
      draw();
    }
    function draw() {
      const [w, h] = size();
      const s = state.scale;
      context.setTransform(1, 0, 0, 1, 0, 0);
      context.fillStyle = '#0f1720';
      context.fillRect(0, 0, canvas.width, canvas.height);
      context.setTransform(s, 0, 0, s, state.x, state.y);
      if (state.image) {
        context.imageSmoothingEnabled = state.zoom < 4;
        // One image pixel a sensor pixel.
        context.drawImage(state.image, 0, 0, state.image.width, state.image.height);
      } else {
        context.fillStyle = '#1e2a36';
        context.fillRect(0, 0, w, h);
      }
      context.strokeStyle = '#5f6b76';
      context.lineWidth = 1 / s;
      context.strokeRect(0, 0, w, h);
      zoomLabel.textContent = `${Math.round(state.zoom * 100)}%`;
      if (!marks.checked) return;
      const r = Math.max(3, 2 * state.zoom) / s;
      context.lineWidth = 1.5 / s;
      state.targets.forEach((t, i) => {
        context.strokeStyle = state.used.has(i) ? '#3ddc84' : '#ff9f1c';
        context.beginPath();
        context.arc(t.x, t.y, r, 0, 2 * Math.PI);
        context.stroke();
      });
      context.strokeStyle = '#4cc9f0';
      const arm = r * 0.8;
      for (const pixels of projected) {
        const p = pixels[state.camera];
        if (!p) continue;
        context.beginPath();
        context.moveTo(p[0] - arm, p[1]); context.lineTo(p[0] + arm, p[1]);
        context.moveTo(p[0], p[1] - arm); context.lineTo(p[0], p[1] + arm);
        context.stroke();
      }
    }
    async function show(camera) {
      state.camera = camera;
      buttons.forEach((b, c) => b.classList.toggle('on', c === camera));
      const body = await getJson(`/sequences/${id}/frames/${frame}/targets?camera=${camera}`);
      state.targets = body.targets;
      state.used = new Set(points.map((p) => p.targets[camera]).filter((t) => t !== null && t !== undefined));
      document.getElementById('target-count').textContent = String(state.targets.length);
      document.getElementById('used-count').textContent = String(state.used.size);
      document.getElementById('reprojected-count').textContent = String(projected.filter((p) => p[camera]).length);
      info.textContent = `(camera ${camera}, ${size()[0]}×${size()[1]} px)`;
      state.image = null;
      fit();
      draw();
      canvas.dataset.camera = String(camera);
      imageNote.textContent = keptImages ? 'Loading the camera image…' : 'This sequence keeps no images: targets and reprojections only.';
      // The camera's kept image, plain, where kept.
      if (keptImages) {
        try {
          const url = `${API}/sequences/${id}/frames/${frame}/image.png?camera=${camera}`;
          const response = await oneAtATime(() => send(url, { headers: headers() }));
          if (!response.ok) throw new HttpError(response.status, response.statusText);
          const bitmap = await createImageBitmap(await response.blob());
          if (state.camera !== camera) return;
          state.image = bitmap;
          imageNote.textContent = 'Under the marks: the camera\'s image as kept.';
          canvas.dataset.image = 'yes';
          draw();
        } catch (error) {
          imageNote.textContent = `No camera image (${error instanceof HttpError ? `HTTP ${error.status}` : 'it does not load'}): targets and reprojections only.`;
        }
      }
    }
    buttons.forEach((b, c) => b.addEventListener('click', () => { show(c).catch(failed); }));
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      const box = canvas.getBoundingClientRect();
      zoomAt(e.deltaY < 0 ? 1.25 : 1 / 1.25, e.clientX - box.left, e.clientY - box.top);
    }, { passive: false });
    let drag = null;
    canvas.addEventListener('pointerdown', (e) => { drag = { x: e.clientX, y: e.clientY }; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag) return;
      state.x += e.clientX - drag.x; state.y += e.clientY - drag.y;
      drag = { x: e.clientX, y: e.clientY };
      draw();
    });
    canvas.addEventListener('pointerup', () => { drag = null; });
    return { node, show };
  }

  /** The frame's particles (and trajectories near it) in 3D: drag to
   * rotate, wheel to zoom; an orthographic view by a rotation matrix. */
  function particleView(points) {
    const canvas = el('canvas', { id: 'view3d', width: 520, height: 520 });
    const context = canvas.getContext('2d');
    const angles = el('span', { id: 'view3d-angles' });
    const node = el('section', { class: 'view3d' },
      el('div', { class: 'toolbar' }, el('b', { text: '3D view' }), el('span', { class: 'note', text: 'drag to rotate, wheel to zoom' }), angles),
      canvas, el('p', { class: 'note', id: 'view3d-note', text: `${points.length} particles; coloured by depth.` }));
    const view = { yaw: 0.6, pitch: 0.35, zoom: 1, trajectories: [] };
    const positions = points.map((p) => [p.x, p.y, p.z]);
    function bounds() {
      const all = positions.concat(...view.trajectories.map((t) => t.points.map((p) => p.position)));
      if (!all.length) return { centre: [0, 0, 0], radius: 1 };
      const low = [0, 1, 2].map((k) => Math.min(...all.map((p) => p[k])));
      const high = [0, 1, 2].map((k) => Math.max(...all.map((p) => p[k])));
      const centre = low.map((l, k) => (l + high[k]) / 2);
      const radius = Math.max(1e-9, Math.hypot(...high.map((h, k) => h - low[k])) / 2);
      return { centre, radius, low, high };
    }
    function rotation() {
      const [cy, sy, cp, sp] = [Math.cos(view.yaw), Math.sin(view.yaw), Math.cos(view.pitch), Math.sin(view.pitch)];
      // R = R_x(pitch) · R_y(yaw): rows are the screen's x, y and depth axes.
      return [[cy, 0, sy], [sp * sy, cp, -sp * cy], [-cp * sy, sp, cp * cy]];
    }
    function draw() {
      const { centre, radius, low, high } = bounds();
      const r = rotation();
      const scale = (0.45 * Math.min(canvas.width, canvas.height) / radius) * view.zoom;
      const project = (p) => {
        const d = [p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]];
        const v = r.map((row) => row[0] * d[0] + row[1] * d[1] + row[2] * d[2]);
        return [canvas.width / 2 + scale * v[0], canvas.height / 2 - scale * v[1], v[2]];
      };
      context.fillStyle = '#0f1720';
      context.fillRect(0, 0, canvas.width, canvas.height);
      if (low) {
        // The bounding box's edges.
        context.strokeStyle = '#33414f';
        context.lineWidth = 1;
        const corner = (i) => [i & 1 ? high[0] : low[0], i & 2 ? high[1] : low[1], i & 4 ? high[2] : low[2]];
        for (let i = 0; i < 8; i++) {
          for (const bit of [1, 2, 4]) {
            if (i & bit) continue;
            const [a, b] = [project(corner(i)), project(corner(i | bit))];
            context.beginPath(); context.moveTo(a[0], a[1]); context.lineTo(b[0], b[1]); context.stroke();
          }
        }
        // Axes from the low corner, a fifth of the box.
        const length = radius * 0.4;
        [['x', '#ff6b6b'], ['y', '#3ddc84'], ['z', '#4cc9f0']].forEach(([label, colour], k) => {
          const tip = low.slice(); tip[k] += length;
          const [a, b] = [project(low), project(tip)];
          context.strokeStyle = colour; context.fillStyle = colour; context.lineWidth = 2;
          context.beginPath(); context.moveTo(a[0], a[1]); context.lineTo(b[0], b[1]); context.stroke();
          context.fillText(label, b[0] + 3, b[1] - 3);
        });
      }
      view.trajectories.forEach((t, i) => {
        context.strokeStyle = `hsl(${(i * 137.5) % 360} 80% 60%)`;
        context.lineWidth = 1.2;
        context.beginPath();
        t.points.forEach((p, k) => {
          const s = project(p.position);
          if (k) context.lineTo(s[0], s[1]); else context.moveTo(s[0], s[1]);
        });
        context.stroke();
      });
      const screen = positions.map(project).sort((a, b) => a[2] - b[2]);
      for (const [x, y, depth] of screen) {
        const t = Math.max(0, Math.min(1, 0.5 + depth / (2 * radius)));
        context.fillStyle = `hsl(${210 - 170 * t} 85% ${45 + 20 * t}%)`;
        context.beginPath();
        context.arc(x, y, 2 + 1.5 * t, 0, 2 * Math.PI);
        context.fill();
      }
      angles.textContent = `yaw ${Math.round((view.yaw * 180) / Math.PI)}°, pitch ${Math.round((view.pitch * 180) / Math.PI)}°`;
    }
    let drag = null;
    canvas.addEventListener('pointerdown', (e) => { drag = { x: e.clientX, y: e.clientY }; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag) return;
      view.yaw += (e.clientX - drag.x) * 0.01;
      view.pitch = Math.max(-Math.PI / 2, Math.min(Math.PI / 2, view.pitch + (e.clientY - drag.y) * 0.01));
      drag = { x: e.clientX, y: e.clientY };
      draw();
    });
    canvas.addEventListener('pointerup', () => { drag = null; });
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      view.zoom = Math.min(20, Math.max(0.2, view.zoom * (e.deltaY < 0 ? 1.2 : 1 / 1.2)));
      draw();
    }, { passive: false });
    draw();
    return {
      node,
      setTrajectories(trajectories) {
        view.trajectories = trajectories;
        document.getElementById('view3d-note').textContent =
          `${points.length} particles; ${trajectories.length} trajectories within 10 frames of this one.`;
        draw();
      },
    };
  }

  function failed(error) {
    if (error instanceof NeedToken) return;
    if (error instanceof HttpError) {
      main.append(el('p', { class: 'problem', text: error.detail }));
      return;
    }
    reportError(`error: ${error && error.message ? error.message : String(error)}`);
  }

  // ---- The router: #/, #/calibrations/ID, #/sequences/ID,
  // #/sequences/ID/frames/N. `body[data-ready]` names the view once shown.
  let generation = 0;
  async function route() {
    cleanups.forEach((cleanup) => cleanup());
    cleanups = [];
    generation += 1;
    const mine = generation;
    document.body.dataset.ready = '';
    const parts = location.hash.replace(/^#\/?/, '').split('/').filter(Boolean);
    const number = (text) => (/^\d+$/.test(text) ? Number(text) : NaN);
    main.replaceChildren(el('p', { class: 'note', text: 'Loading…' }));
    try {
      if (!parts.length) await home();
      else if (parts[0] === 'calibrations' && parts.length === 2 && number(parts[1]) >= 0) await calibrationPage(number(parts[1]));
      else if (parts[0] === 'sequences' && parts.length === 2 && number(parts[1]) >= 0) await sequencePage(number(parts[1]));
      else if (parts[0] === 'sequences' && parts.length === 4 && parts[2] === 'frames' && number(parts[1]) >= 0 && number(parts[3]) >= 0) {
        await framePage(number(parts[1]), number(parts[3]));
      } else main.replaceChildren(el('p', { class: 'problem', text: `No such page: ${location.hash}` }));
    } catch (error) {
      if (mine === generation) {
        if (error instanceof HttpError) main.replaceChildren(el('p', { class: 'problem', text: error.detail }));
        else if (error instanceof NeedToken) {
          main.replaceChildren(el('p', { class: 'note', id: 'needs-token', text: 'This view needs the API token: give it above.' }));
        } else { main.replaceChildren(); failed(error); }
      }
    }
    if (mine === generation) {
      const view = parts.join('/') || 'home';
      performance.mark(`ready ${view}`);
      document.body.dataset.ready = view;
    }
  }
  window.addEventListener('hashchange', route);
  showForget();
  route();
})();
