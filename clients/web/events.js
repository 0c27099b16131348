/*
 * The selected map's event stream (GET maps/{id}/events?robots=delta, an EventSource): openEvents
 * hands its events to the tiles (`tiles`), the robots (`robots`, `robots_delta`) and the map
 * selection (`replaced`, `deleted`), and reconnects: by itself while the browser retries, after
 * RECONNECT_MS (or the service's Retry-After) when the browser gave up, and with every tile and robot
 * loaded again after any break. A hidden tab closes its stream until it is shown again
 * (pauseWhileHidden). The stream's `keepalive` events break every silence, so one that says nothing
 * for SILENT_STREAM_INTERVALS of them is dead though the browser thinks it open: it is opened again
 * (watchSilence).
 */
import { MAX_RETRY_AFTER_MS, RECONNECT_MS, SILENT_STREAM_INTERVALS } from './config.js';
import { deselectMap, refreshMaps, reloadMap } from './maps.js';
import { enc, errorDetail } from './rest.js';
import { applyRobotsDelta, updateRobots } from './robots.js';
import { needSignIn } from './signin.js';
import { state } from './state.js';
import { clearNetworkError, renderStatus, setConnection, showError } from './status.js';
import { queueTiles } from './tiles.js';

/** Close the selected map's event stream, and cancel a reconnect planned for it. */
export function closeEvents() {
  clearTimeout(state.reconnectTimer);
  state.reconnectTimer = null;
  clearTimeout(state.silenceTimer);
  state.silenceTimer = null;
  if (state.events) state.events.close();
  state.events = null;
}

/**
 * Open map `mapId`'s event stream in place of any other (unless the tab is hidden: see
 * pauseWhileHidden). `since`: the map's change version when the page read it, before it asked for
 * its tiles (a selection's first stream): the stream tells of every change from then. Started from
 * the version when it opened instead, it said nothing of a scan that changed tiles already loaded
 * while it was on its way, and those tiles stayed stale.
 */
export function openEvents(mapId, since = null) {
  closeEvents();
  if (document.visibilityState === 'hidden') {
    // Nobody looks: no stream until the tab is shown (see the visibilitychange listener). The map
    // changes meanwhile and the stream, opened then, reports only later changes: catch up when it
    // opens, as after a break (a page opened in a background tab kept its first tiles for good).
    state.eventsBroken = true;
    setConnection('paused');
    return;
  }
  setConnection('connecting');
  const from = Number.isSafeInteger(since) && since >= 0 ? `&since=${since}` : '';
  const es = new EventSource(`maps/${enc(mapId)}/events?robots=delta&keepalive=event${from}`);
  state.events = es;
  let interval = 0; // seconds between the stream's keepalives, once its first one said
  // Anything the stream sends shows it alive: wait for the next thing, at most a few keepalives long.
  const alive = () => {
    clearTimeout(state.silenceTimer);
    if (interval > 0) state.silenceTimer = setTimeout(silent, SILENT_STREAM_INTERVALS * interval * 1000);
  };
  // Nothing came for too long: the connection died without a FIN or RST, and the browser, which
  // never times a stream out, would show this stale map as live for good. Open another stream,
  // catching up as after any break.
  const silent = () => {
    if (es !== state.events) return;
    state.eventsBroken = true;
    setConnection('reconnecting');
    openEvents(mapId);
  };
  es.onopen = () => {
    if (es !== state.events) return;
    setConnection('connected');
    clearNetworkError();
    // After a break the service may have restarted with another map under this id (restored from
    // another backup: other resolution, other layers, other robots). Load it again as a `replaced`
    // event does, then redraw every tile; rare, and always right.
    if (state.eventsBroken) reloadMap(false, true);
    state.eventsBroken = false;
  };
  es.onerror = () => {
    if (es !== state.events) return;
    state.eventsBroken = true;
    // The break is known: the browser's retry, or ours below, takes over from the silence watch.
    clearTimeout(state.silenceTimer);
    if (es.readyState === EventSource.CLOSED) {
      // The browser gave up (e.g. an HTTP error): try again ourselves after a pause.
      setConnection('error');
      explainStreamError(es.url, mapId);
      state.reconnectTimer = setTimeout(() => {
        if (state.mapId === mapId) openEvents(mapId);
      }, RECONNECT_MS);
    } else {
      setConnection('reconnecting'); // EventSource retries by itself
    }
  };
  const handle = (fn) => (e) => {
    if (es !== state.events) return;
    let data;
    try {
      data = JSON.parse(e.data);
    } catch (err) {
      showError(`bad ${e.type} event: ${err.message}`);
      return;
    }
    alive();
    state.lastUpdate = new Date();
    renderStatus();
    fn(data);
  };
  es.addEventListener('keepalive', (e) => {
    if (es !== state.events) return;
    let sent = 0;
    try {
      sent = Number(JSON.parse(e.data).interval);
    } catch (_) {
      // Not this service's keepalive: it still shows the stream alive.
    }
    if (sent > 0) interval = sent;
    alive();
  });
  es.addEventListener('tiles', handle(queueTiles));
  es.addEventListener('robots', handle((d) => updateRobots(d.robots, true)));
  es.addEventListener('robots_delta', handle(applyRobotsDelta));
  // The map was replaced under its id (a snapshot upload): stay on it and reload it; the stream
  // goes on with the new map's events.
  es.addEventListener('replaced', handle(() => reloadMap()));
  // The map was deleted: the stream ends; the map list poll picks another map (or waits).
  es.addEventListener('deleted', handle(() => {
    deselectMap();
    showError(`map ${mapId} was deleted`);
    refreshMaps();
  }));
}

/**
 * An EventSource that the browser gave up on says nothing of why: ask the service the same URL and
 * show its answer (e.g. 503: it holds its limit of open event streams), else the page would only
 * say 'retrying' forever. A 200 is a stream that works again: closed at once, the retry opens it.
 * The message goes when the stream opens (clearNetworkError).
 */
async function explainStreamError(url, mapId) {
  const ctl = new AbortController();
  try {
    const resp = await fetch(url, { cache: 'no-store', signal: ctl.signal });
    if (resp.ok || state.mapId !== mapId || state.connection !== 'error') return;
    if (resp.status === 401) {
      needSignIn(); // the session's token was revoked
      return;
    }
    // The service says when to come back (Retry-After: 5 s while it holds its limit of streams):
    // the retry waits that long rather than RECONNECT_MS, as docs/api.md asks of every client.
    const wait = 1000 * Number(resp.headers.get('Retry-After'));
    if (wait > RECONNECT_MS && wait <= MAX_RETRY_AFTER_MS && state.reconnectTimer !== null) {
      clearTimeout(state.reconnectTimer);
      state.reconnectTimer = setTimeout(() => {
        if (state.mapId === mapId) openEvents(mapId);
      }, wait);
    }
    showError(`event stream: ${resp.status} ${await errorDetail(resp)}`, true);
  } catch (_) {
    // Unreachable: the map list poll says so.
  } finally {
    ctl.abort();
  }
}

/** Close the stream while the tab is hidden, and catch up when it is shown. */
export function pauseWhileHidden() {
  // A hidden tab shows nothing, so it costs nothing: it closes its event stream (and pumpTiles
  // requests no tile) until it is shown again, then catches up as after a reconnect: the map's
  // metadata and robots again, and every tile once.
  document.addEventListener('visibilitychange', () => {
    if (!state.mapId) return;
    if (document.visibilityState === 'hidden') {
      if (state.connection === 'paused') return;
      closeEvents();
      state.eventsBroken = true;
      setConnection('paused');
    } else if (state.connection === 'paused') {
      openEvents(state.mapId);
    }
  });
}
