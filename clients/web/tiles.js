/*
 * The live tile layer and its refresh rules (the app.js header, "Live refresh"): `tiles`, whose URLs
 * carry the map, the layer and the version counter; state.shownTiles, the tiles on the map and whether
 * each one's request is under way (trackShownTiles keeps it); queueTiles, which takes a `tiles`
 * event's changed windows (or a reset) and, at most every TILE_FLUSH_MS, marks the tiles they touch
 * stale; pumpTiles, which gives a stale tile a new URL once it is due. Until the user moves the map,
 * the view also follows the map as it grows (followSoon).
 */
import { refreshCell } from './cell.js';
import {
  FOLLOW_MS, MAX_ZOOM, MIN_ZOOM, TILE_FLUSH_MS, TILE_PX, TILE_REFRESH_MS, TILE_RETRY_MS,
} from './config.js';
import { map, windowInView } from './leaflet-map.js';
import { refreshInfo, showNoScans } from './maps.js';
import { enc } from './rest.js';
import { state } from './state.js';
import { clearError, showError } from './status.js';

// A per-page-load prefix for tile versions: a map deleted and re-created restarts its versions,
// and a reloaded page must not hit tiles an earlier page load left in the browser cache.
const PAGE_STAMP = Date.now().toString(36);
// A transparent image (unknown cells look the same): a failed tile's, and a held one's (below).
const BLANK_TILE = 'data:image/gif;base64,R0lGODlhAQABAIAAAAAAAP///yH5BAEAAAAALAAAAAABAAEAAAIBRAA7';

/** The tile layer: its URL carries the map, the layer and the version counter. */
const FleetTiles = L.TileLayer.extend({
  createTile(coords, done) {
    const img = L.TileLayer.prototype.createTile.call(this, coords, done);
    // Decode the PNG off the main thread; the tile shows its last image until the new one is ready.
    img.decoding = 'async';
    return img;
  },
  getTileUrl(coords) {
    // While a reloaded map's layers are unknown (state.tilesHeldBy), the layer shown may be one it no
    // longer keeps: a tile Leaflet makes meanwhile (the user panned or zoomed) shows nothing, where it
    // was asked for and refused (422), until the reload's reset asks for every tile (reloadMap).
    if (state.tilesHeldBy) return BLANK_TILE;
    const v = `${PAGE_STAMP}-${state.tileCounter}`;
    return `maps/${enc(state.mapId)}/tiles/${coords.z}/${coords.x}/${coords.y}.png` +
      `?layer=${enc(state.layer)}&v=${v}`;
  },
});
export const tiles = new FleetTiles('', {
  tileSize: TILE_PX,
  minZoom: MIN_ZOOM,
  maxZoom: MAX_ZOOM,
  maxNativeZoom: MAX_ZOOM,
  minNativeZoom: MIN_ZOOM,
  noWrap: true,
  keepBuffer: 1,
  // A failed tile: a transparent image, never the broken-image icon.
  errorTileUrl: BLANK_TILE,
});

/**
 * Keep state.shownTiles in step with the tiles on the map, and refresh stale tiles as they come into
 * view.
 */
export function trackShownTiles() {
  // Keep our own list of tile elements on the map (public events, not Leaflet's private _tiles),
  // with whether each one's request is still under way.
  tiles.on('tileloadstart', (e) => {
    const tile = {
      el: e.tile, coords: e.coords, loading: true, stale: false, reset: false, requestedAt: performance.now(),
      retryAt: 0,
    };
    state.shownTiles.set(`${e.coords.x}:${e.coords.y}:${e.coords.z}`, tile);
    const done = () => {
      tile.loading = false;
      if (tile.stale) schedulePump(0);
    };
    e.tile.addEventListener('load', () => {
      // Asked again and loaded, the tile no longer failed (the message stayed 15 s). Not when the
      // image that loaded is the errorTileUrl Leaflet puts in a failed tile's place.
      if (e.tile.getAttribute('src') !== tiles.options.errorTileUrl) clearError(failedMessage(e.coords));
      done();
    });
    // A failed tile shows nothing (errorTileUrl), and nothing else would ask for it again until its
    // cells change, on a finished map never: a network blip left holes in the map. Ask again after
    // TILE_RETRY_MS, while the stream is connected (a reconnect reloads every tile anyway).
    e.tile.addEventListener('error', () => {
      tile.stale = true;
      tile.retryAt = performance.now() + TILE_RETRY_MS;
      done();
    });
  });
  // A tile still loading when the zoom changes is aborted: Leaflet takes it off the map and says
  // 'tileabort', not 'tileunload'. Kept here, a reset (reconnect, replaced map) asked for it again.
  const forgetTile = (e) => {
    const key = `${e.coords.x}:${e.coords.y}:${e.coords.z}`;
    if (state.shownTiles.get(key)?.el === e.tile) state.shownTiles.delete(key);
  };
  tiles.on('tileunload', forgetTile);
  tiles.on('tileabort', forgetTile);
  tiles.on('tileerror', (e) => {
    // A tile that fails (e.g. the map was deleted, the service is down) shows the transparent
    // errorTileUrl, not a broken image; say why, unless the status line already does (no stream).
    if (state.mapId && state.connection === 'connected') {
      showError(failedMessage(e.coords));
    }
  });

  // A stale tile that comes into view (pan, zoom) is due at once.
  map.on('moveend', () => schedulePump(0));
}

/** What the page says of a tile that failed to load. */
function failedMessage(c) {
  return `tile ${c.z}/${c.x}/${c.y} failed to load`;
}

/** The cell window [i0, j0, i1, j1) a tile covers (tile_render.tile_window without the step). */
function tileCells(c) {
  const s = TILE_PX / Math.pow(2, c.z);
  return [c.x * s, -(c.y + 1) * s, (c.x + 1) * s, -c.y * s];
}

function intersects(a, b) {
  return a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
}

/** Queue changed windows (or a reset) and schedule one throttled flush. */
export function queueTiles(msg) {
  // Cells arrived: the map is no longer empty.
  if (Array.isArray(msg.tiles) && msg.tiles.length) showNoScans(false);
  if (msg.reset) state.pendingReset = true;
  else if (Array.isArray(msg.tiles)) state.pendingWindows.push(...msg.tiles);
  if (state.flushTimer === null) {
    const wait = Math.max(0, state.lastFlush + TILE_FLUSH_MS - Date.now());
    state.flushTimer = setTimeout(flushTiles, wait);
  }
}

/** Reload the displayed tiles the queued windows touch (all of them after a reset). */
function flushTiles() {
  state.flushTimer = null;
  state.lastFlush = Date.now();
  const windows = state.pendingWindows;
  const reset = state.pendingReset;
  state.pendingWindows = [];
  state.pendingReset = false;
  if (!state.mapId) return;
  refreshCell(windows, reset);
  if (!map.hasLayer(tiles)) return;
  state.tileCounter += 1;
  for (const tile of state.shownTiles.values()) {
    if (reset || windows.some((w) => intersects(tileCells(tile.coords), w))) tile.stale = true;
    if (reset) tile.reset = true;
  }
  schedulePump(0);
  // The first scans of a map: fit the view once the map has bounds.
  if (!state.fitted && !state.infoInFlight) {
    state.infoInFlight = true;
    refreshInfo(state.selectToken, false).finally(() => { state.infoInFlight = false; });
  } else if (state.fitted && !state.viewChosen && windows.some((w) => !windowInView(w))) {
    followSoon(); // cells changed out of view: the map may have outgrown the fitted view
  }
}

/**
 * Until the user moves the map, the view follows it as it grows: look its bounds up again
 * (refreshInfo refits the view when they no longer fit), at most once per FOLLOW_MS, and after
 * the last change too (a throttled look that were simply dropped would miss the robots' last room).
 */
function followSoon() {
  if (state.followTimer !== null) return;
  const wait = Math.max(0, state.followedAt + FOLLOW_MS - performance.now());
  state.followTimer = setTimeout(() => {
    state.followTimer = null;
    if (state.viewChosen || !state.mapId) return;
    if (state.infoInFlight) {
      followSoon();
      return;
    }
    state.followedAt = performance.now();
    state.infoInFlight = true;
    refreshInfo(state.selectToken, false).finally(() => { state.infoInFlight = false; });
  }, wait);
}

/** Look for due stale tiles in `delay` ms, unless a look is already planned sooner. */
function schedulePump(delay) {
  const at = performance.now() + delay;
  if (at >= state.pumpAt) return;
  clearTimeout(state.pumpTimer);
  state.pumpAt = at;
  state.pumpTimer = setTimeout(pumpTiles, delay);
}

/**
 * Whether a stale tile is worth a request: it is at the current zoom (not one Leaflet keeps until
 * the new zoom's tiles have loaded) and in the view, or anywhere after a reset (a new map: no tile
 * Leaflet keeps around the view may show the old one when it comes into view).
 */
function tileWanted(tile) {
  const coords = tile.coords;
  if (coords.z !== map.getZoom()) return false;
  if (tile.reset) return true;
  const view = map.getPixelBounds();
  const x0 = coords.x * TILE_PX;
  const y0 = coords.y * TILE_PX;
  return x0 < view.max.x && x0 + TILE_PX > view.min.x && y0 < view.max.y && y0 + TILE_PX > view.min.y;
}

/**
 * Request the stale tiles that are due again (see the header comment), and plan the next look for
 * the ones that are not due yet. Setting src keeps the old image on screen until the new one has
 * arrived: no blinking.
 */
function pumpTiles() {
  state.pumpTimer = null;
  state.pumpAt = Infinity;
  if (document.visibilityState === 'hidden' || !state.mapId || !map.hasLayer(tiles)) return;
  if (state.tilesHeldBy) return; // the map is being loaded again: its layers are not known yet (reloadMap)
  const now = performance.now();
  let next = Infinity;
  for (const tile of state.shownTiles.values()) {
    if (!tile.stale || tile.loading || !tileWanted(tile)) continue;
    if (tile.retryAt && state.connection !== 'connected') continue;
    const due = Math.max(tile.requestedAt + TILE_REFRESH_MS, tile.retryAt);
    if (due > now) {
      next = Math.min(next, due);
      continue;
    }
    tile.stale = false;
    tile.reset = false;
    tile.loading = true;
    tile.requestedAt = now;
    tile.retryAt = 0;
    tile.el.src = tiles.getTileUrl(tile.coords);
  }
  if (next < Infinity) schedulePump(next - now);
}
