/*
 * The map selector and the selected map: the map list (polled, refreshMaps), selecting a map and
 * forgetting it (selectMap, deselectMap), loading a replaced one again (reloadMap), and its
 * GET maps/{id} (refreshInfo: resolution, layers, robots, and the bounds the view is fitted to).
 * Answers for a map no longer selected are dropped (state.selectToken).
 */
import { clearCell } from './cell.js';
import { MAP_RETRY_MS, RECONNECT_SPREAD_MS } from './config.js';
import { emptyEl, layerSelect, mapSelect, noScansEl, noScansKey, signInEl } from './dom.js';
import { closeEvents, openEvents } from './events.js';
import { readHash } from './hash.js';
import { setLayerOptions } from './layers.js';
import { boundsInView, map, moveQuietly, showView, toLatLng } from './leaflet-map.js';
import { enc, getJSON } from './rest.js';
import { clearRobots, naturalOrder, redrawRobots, updateRobots } from './robots.js';
import { state } from './state.js';
import { clearError, clearNetworkError, setConnection, showError } from './status.js';
import { queueTiles, tiles } from './tiles.js';

/** stats.bounds (metres) as [xmin, ymin, xmax, ymax], accepting a list or an object; null if none. */
function normBounds(b) {
  if (!b) return null;
  if (Array.isArray(b) && b.length === 4) return b.map(Number);
  if (typeof b === 'object') {
    if ('xmin' in b) return [b.xmin, b.ymin, b.xmax, b.ymax].map(Number);
    if (Array.isArray(b.min) && Array.isArray(b.max)) return [b.min[0], b.min[1], b.max[0], b.max[1]].map(Number);
  }
  return null;
}

/** The hint over a map with no scans yet: what to publish, and where. */
export function showNoScans(show) {
  if (show && state.mapId) {
    const v = document.createElement('var');
    v.textContent = 'ROBOT';
    noScansKey.replaceChildren(`fleetmap/${state.mapId}/`, v, '/scan');
  }
  noScansEl.hidden = !(show && state.mapId);
}

/** Poll the map list; keep the selection, pick one when there is none. */
export async function refreshMaps() {
  if (!signInEl.hidden) return; // refused until the user signs in (the form asks again then)
  let ids;
  try {
    const body = await getJSON('maps');
    const items = Array.isArray(body) ? body : (body.maps || []);
    // In natural order, as the robots are: warehouse-2 before warehouse-10, and case aside.
    ids = items.map((m) => (typeof m === 'string' ? m : m.id)).filter(Boolean).sort(naturalOrder.compare);
  } catch (err) {
    showError(`map list: ${err.message}`, !!err.network);
    // With a map shown its event stream's state says as much; with none the status said 'waiting
    // for robots' while nothing could be waited for.
    if (err.network && !state.mapId) setConnection('unreachable');
    return;
  }
  // The service answers: 'cannot reach' is no longer true (it stayed 15 s). A stream in trouble
  // keeps its own reason (e.g. its 503) until it opens.
  if (!state.mapId || state.connection === 'connected') clearNetworkError();
  const current = [...mapSelect.options].map((o) => o.value);
  if (ids.join('\n') !== current.join('\n')) setMapOptions(ids);
  mapSelect.disabled = ids.length === 0;
  emptyEl.hidden = ids.length > 0;
  if (ids.length === 0) {
    // The map shown is gone and no `deleted` event said so (the stream was down: a restart, a
    // hidden tab): say it, as below where another map is left, rather than vanish without a word.
    const gone = state.mapId;
    if (gone) deselectMap();
    setConnection('waiting');
    // A link to a map that does not exist (yet): say so once; it is shown as soon as it appears.
    const wanted = readHash().map;
    if (gone) showError(`map ${gone} was deleted`);
    else if (wanted && state.notFound !== wanted) showError(`map ${wanted} not found`);
    state.notFound = wanted;
    return;
  }
  if (state.mapId && ids.includes(state.mapId)) {
    mapSelect.value = state.mapId;
    return;
  }
  const wanted = readHash().map;
  if (state.mapId) showError(`map ${state.mapId} was deleted`);
  else if (wanted && !ids.includes(wanted)) showError(`map ${wanted} not found`);
  // The selection rewrites the hash: the URL names the map shown.
  selectMap(ids.includes(wanted) ? wanted : ids[0]);
}

/** The map selector's options: the ids, or '(no maps)'. */
export function setMapOptions(ids) {
  mapSelect.replaceChildren(...(ids.length ? ids : ['']).map((id) => {
    const o = document.createElement('option');
    o.value = id;
    o.textContent = id || '(no maps)';
    return o;
  }));
}

/**
 * No map to show (the shown one was deleted): nothing of it stays on the page or in the URL.
 * `keepHash`: the URL keeps naming the map and view, to show them again (after signing in again).
 */
export function deselectMap(keepHash = false) {
  state.selectToken += 1; // answers still on their way are for a map no longer shown
  state.mapId = null;
  state.info = null;
  state.viewChosen = false;
  state.lastUpdate = null; // the status line's 'last update' was of the map no longer shown
  closeEvents();
  clearRobots();
  clearCell();
  showNoScans(false);
  if (map.hasLayer(tiles)) tiles.remove();
  layerSelect.replaceChildren();
  layerSelect.disabled = true;
  if (location.hash && !keepHash) history.replaceState(null, '', location.pathname + location.search);
}

/** Switch to a map: its layers, its tiles, its robots, its event stream. */
export async function selectMap(mapId) {
  const token = ++state.selectToken;
  closeEvents();
  clearRobots();
  state.mapId = mapId;
  state.info = null;
  state.lastUpdate = null; // of the map shown before: this one's first event comes at once
  // The stream of the map shown before is closed: the status line no longer says 'connected' (it
  // did until this map's GET answered, and for good if that failed). openEvents says what follows.
  setConnection('connecting');
  // New tile URLs: the browser keeps the images of URLs this page loaded and shows them again
  // without asking (no-cache or not), so a map shown before, changed meanwhile (or deleted and
  // made again under its id), kept its old tiles under the counter they were loaded with.
  state.tileCounter += 1;
  state.fitted = false;
  state.eventsBroken = false;
  state.tilesHeldBy = 0; // a reload of the map shown before no longer holds tiles back
  // A link's view belongs to the map it names; another map is fitted to its bounds.
  const linked = readHash();
  state.pendingView = linked.map === mapId ? linked.view : null;
  state.viewChosen = state.pendingView !== null;
  mapSelect.value = mapId;
  clearError(`map ${mapId} not found`); // said while a link waited for it
  showNoScans(false);
  clearCell();
  if (map.hasLayer(tiles)) tiles.remove();
  const ok = await refreshInfo(token, true);
  if (token !== state.selectToken) return;
  if (!ok) {
    state.mapId = null; // the next map-list poll tries again
    return;
  }
  tiles.addTo(map);
  // From the version read with the map, before any of its tiles: a change while the stream is on
  // its way is told, not lost.
  openEvents(mapId, state.info.stats?.version);
}

/**
 * The selected map was replaced under its id: its configuration (layers, resolution), cells and
 * robots are new. Forget what the page knew of the old one and load it again, as a selection does,
 * but keep the event stream (it goes on with the new map) and the map selector as they are.
 * `spread`: reload the tiles after a random delay of up to RECONNECT_SPREAD_MS (after a reconnect).
 * A failed GET is tried again every MAP_RETRY_MS, with no tile asked for, until it answers or the
 * page leaves the map (another selection) or reloads it again.
 */
export async function reloadMap(refit = true, spread = false) {
  const token = state.selectToken;
  // Until the map's GET answers, the layer shown may be one the new map does not keep: no tile is
  // asked for meanwhile (pumpTiles). Its tiles events came first on a slow service, and every tile
  // they touched was refused (422), left blank, each with a 'failed to load' message; the reset
  // below asks for every tile once the layers are known.
  const reload = ++state.reloads;
  state.tilesHeldBy = reload;
  clearRobots();
  // A replaced map may lie elsewhere; after a reconnect keep the user's view unless the
  // resolution changed (refreshInfo refits then: the same cell indices are other places).
  if (refit) state.fitted = false;
  clearCell();
  // Until the GET answers: a failed one (the service overloaded for a moment) is asked again. Given
  // up, the page kept the old map's layers and asked for its tiles in a layer the new map may not
  // keep, each refused (422) every TILE_RETRY_MS for good. Tiles stay held meanwhile. A newer reload,
  // or another selection (a deleted map, a sign-in form), takes over.
  const superseded = () => token !== state.selectToken || reload !== state.reloads;
  while (!(await refreshInfo(token, true))) {
    if (superseded()) return;
    await new Promise((resolve) => { setTimeout(resolve, MAP_RETRY_MS); });
    if (superseded()) return;
  }
  if (state.tilesHeldBy === reload) state.tilesHeldBy = 0;
  // Every tile, after the layer selector knows the new map's layers (the layer may have changed).
  const reset = () => { if (token === state.selectToken) queueTiles({ reset: true }); };
  if (spread) setTimeout(reset, Math.random() * RECONNECT_SPREAD_MS);
  else reset();
}

/** GET maps/{id}: layers, resolution, bounds (fitted, and again as the map grows until the user
 * moves it), robots. Returns false on failure. */
export async function refreshInfo(token, first) {
  const mapId = state.mapId;
  let info;
  try {
    info = await getJSON(`maps/${enc(mapId)}`);
  } catch (err) {
    // Only of the map still shown: a slow answer for one the user has left is no news of this one.
    if (token === state.selectToken) showError(`map ${mapId}: ${err.message}`, !!err.network);
    return false;
  }
  if (token !== state.selectToken) return false;
  state.info = info;
  const config = info.config || {};
  if (first) {
    const res = Number(config.resolution) || 0.05;
    if (res !== state.res) {
      state.fitted = false;
      state.res = res;
      redrawRobots(); // robot events may have come in since, placed with the old resolution
    }
    setLayerOptions(config.layers);
    const stats = info.stats || {};
    if (stats.robots) {
      // Only robots the stream has not shown yet: what it sent may be newer than this answer,
      // and with deltas a robot that does not change again would keep a stale report.
      const reports = Object.create(null); // a robot may be called __proto__ (see applyRobotsDelta)
      for (const [id, r] of Object.entries(stats.robots)) {
        if (state.robots.has(id)) continue;
        reports[id] = { online: r.online, pose: r.last_pose, scans_integrated: r.scans_integrated };
      }
      updateRobots(reports);
    }
  }
  const b = normBounds(info.stats && info.stats.bounds);
  // No known cell yet: say what would fill the map (the tiles event of the first scan hides it).
  showNoScans(!b);
  if (first && state.pendingView) {
    // A link named the view: show it, never fit over it.
    showView(state.pendingView);
    state.pendingView = null;
    state.fitted = true;
  } else if (b && (!state.fitted || (!state.viewChosen && !boundsInView(b)))) {
    state.fitted = true;
    moveQuietly(() => map.fitBounds([toLatLng(b[0], b[1]), toLatLng(b[2], b[3])],
      { padding: [20, 20], maxZoom: 2, animate: false }));
  } else if (first && !b && !state.viewChosen) {
    moveQuietly(() => map.setView([0, 0], 0, { animate: false }));
  }
  return true;
}

/** Select the map the user picks. */
export function selectMapOnChange() {
  mapSelect.addEventListener('change', () => {
    if (mapSelect.value && mapSelect.value !== state.mapId) selectMap(mapSelect.value);
  });
}
