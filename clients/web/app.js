/*
 * fleetmap web viewer: plain JavaScript on Leaflet, no build step.
 *
 * What it shows and where it gets it (all URLs relative to the page, so a path prefix works):
 *   GET maps                      -> the map selector (refreshed every MAPS_REFRESH_MS)
 *   GET maps/{id}                 -> config.layers (layer selector), config.resolution, stats.bounds (fit),
 *                                    stats.robots (initial robot list)
 *   GET maps/{id}/tiles/{z}/{x}/{y}.png?layer=L&v=V
 *                                 -> the map itself on L.CRS.Simple: one map unit = one CELL,
 *                                    lng = cell x index i, lat = cell y index j, zoom 0 = one pixel per cell
 *   GET maps/{id}/events?robots=delta (SSE)
 *                                 -> `tiles` {version, tiles: [[i0, j0, i1, j1], ...]} or {version, reset},
 *                                    `robots` {robots: {id: {online, pose, trail, scans_integrated}}}
 *                                    (every robot: first, and after `replaced`), then
 *                                    `robots_delta` {trail_length, robots: {id: {..., trail: the
 *                                    points appended since}}, removed: [id, ...]} (what changed),
 *                                    `replaced` {id, version} (same map id, new content: reload it),
 *                                    `deleted` {id}
 *   GET maps/{id}/cell?x=&y=      -> the values of the clicked cell
 *   POST session, DELETE session  -> sign in and out, where the service needs a token to read (below)
 *
 * The selected map and layer live in the URL hash: #map=<id>&layer=<layer>; once the user moves the
 * map, the view too: &x=<metres>&y=<metres>&z=<zoom> (the centre), so a link shows the same place.
 *
 * Live refresh: the `v` query parameter of a tile URL is a counter this page bumps whenever tiles
 * change. A displayed tile whose cells intersect a changed window is marked stale, and a stale tile
 * gets a new URL (so a new request, never a stale browser-cache hit) only when (a) it is in view,
 * (b) its previous request has finished, (c) TILE_REFRESH_MS have passed since that request began,
 * and (d) the page is visible. So a tile that changes 50 times a second is fetched at most
 * 1000 / TILE_REFRESH_MS times a second, a slow service is never asked for a tile it is still
 * rendering, and a hidden tab fetches nothing (it also closes its event stream until shown again).
 * Tiles created later use the newest counter. A tile that failed to load is stale again, due
 * TILE_RETRY_MS later (while the event stream is connected; a reconnect reloads every tile anyway).
 *
 * Signing in: a service run with --require-read-token answers every read 401 without a token, and
 * neither an <img> tile nor an EventSource can send one. A 401 shows a form (over the map) whose token
 * is posted once to `session` in an Authorization header; the service answers with a session cookie
 * (HttpOnly: this page never sees it) that the browser then sends with every request, tiles and the
 * event stream included. The page keeps no token. A 401 later (the token was revoked) shows the form
 * again; with reads open no request is ever refused, and the page never shows it.
 *
 * Robots are drawn incrementally: a robot's marker and trail are made once, then moved and turned in
 * place, and only when its report changed; a robot the service no longer reports is removed. The
 * stream sends only the robots that changed and their new trail points (`robots_delta`), so 100
 * robots moving at 2 Hz cost ~30 kB a second instead of 0.5 to 1.5 MB.
 */
(function () {
  'use strict';

  // ---- constants -------------------------------------------------------------------------------

  const TILE_PX = 256;            // tile size in pixels (the service's tile_render.TILE_PX)
  const MIN_ZOOM = -8;            // 256 cells per pixel
  const MAX_ZOOM = 4;             // 16 pixels per cell; the service renders zooms -8..4
  // The farthest point (metres from the origin, on x and on y) a typed point or a link's view may
  // name. Farther, Leaflet's pixel arithmetic fails: 1e308 m is an infinite number of cells (it
  // threw, and the map was never shown), 1e16 m at zoom 4 asked for so many tiles that the tab died.
  const MAX_METRES = 1e7;
  const MAPS_REFRESH_MS = 5000;   // how often the map list is polled
  const TILE_FLUSH_MS = 100;      // changed windows are applied to the tiles at most this often
  const TILE_REFRESH_MS = 500;    // one tile is requested again at most this often (2 per second)
  const TILE_RETRY_MS = 3000;     // a tile that failed to load is asked for again after this long
  const RECONNECT_MS = 3000;      // retry delay when the browser gives up on the event stream
  const MAX_RETRY_AFTER_MS = 60000; // the longest a refusal's Retry-After holds the stream's retry back
  // Until the user moves the map, the view follows the map as it grows (a demo's robots explore
  // beyond the first fit): its bounds are looked up at most this often while tiles change.
  const FOLLOW_MS = 2000;
  // After a reconnect every tile is reloaded once; spread over this many ms, so that the viewers of a
  // restarted service do not all ask it for their tiles in the same instant.
  const RECONNECT_SPREAD_MS = 1000;
  const ERROR_SHOW_MS = 15000;    // how long an error message stays visible
  // localStorage key set while this browser holds a session (so a reloaded page offers "Sign out":
  // the cookie itself is HttpOnly, out of the page's reach).
  const SIGNED_IN_KEY = 'fleetmap.signedIn';
  // What a token may hold (fleetmap.auth): printable ASCII, no space.
  const TOKEN_CHARS = /^[\x21-\x7e]+$/;

  // Tile layers the service renders, and the map layer (config.layers) each one needs.
  const LAYERS = [
    { name: 'probability', needs: 'occupancy', label: 'probability' },
    { name: 'state', needs: 'occupancy', label: 'state (free / occupied)' },
    { name: 'log_odds', needs: 'occupancy', label: 'log odds' },
    { name: 'hits', needs: 'counts', label: 'hits' },
    { name: 'misses', needs: 'counts', label: 'misses' },
    { name: 'tsdf', needs: 'tsdf', label: 'TSDF' },
    { name: 'tsdf_weight', needs: 'tsdf', label: 'TSDF weight' },
  ];

  // Cell fields shown on click, in this order.
  const CELL_FIELDS = ['known', 'probability', 'state', 'log_odds', 'hits', 'misses', 'tsdf', 'tsdf_weight'];

  // A per-page-load prefix for tile versions: a map deleted and re-created restarts its versions,
  // and a reloaded page must not hit tiles an earlier page load left in the browser cache.
  const PAGE_STAMP = Date.now().toString(36);

  // ---- elements --------------------------------------------------------------------------------

  const $ = (id) => document.getElementById(id);
  const mapSelect = $('map-select');
  const layerSelect = $('layer-select');
  const statusEl = $('status');
  const statusTextEl = $('status-text');
  const lastUpdateEl = $('last-update');
  const coordsEl = $('coords');
  const emptyEl = $('empty');
  const noScansEl = $('no-scans');
  const noScansKey = $('no-scans-key');
  const robotList = $('robot-list');
  const robotCount = $('robot-count');
  const cellInfo = $('cell-info');
  const cellForm = $('cell-form');
  const cellX = $('cell-x');
  const cellY = $('cell-y');
  const cellFormError = $('cell-form-error');
  const cellAnnounce = $('cell-announce');
  const sideToggle = $('side-toggle');
  const sideSummary = $('side-summary');
  const errorEl = $('error');
  const signInEl = $('sign-in');
  const signInForm = $('sign-in-form');
  const signInToken = $('sign-in-token');
  const signInError = $('sign-in-error');
  const signOutButton = $('sign-out');

  // ---- state -----------------------------------------------------------------------------------

  const state = {
    mapId: null,          // selected map id
    layer: null,          // selected tile layer name
    info: null,           // last GET maps/{id} answer
    res: 0.05,            // metres per cell of the selected map
    fitted: false,        // view fitted to the map's bounds (again as it grows, until the user moves it)
    followedAt: -Infinity, // when the bounds were last looked up to follow the growing map
    followTimer: null,    // the next such look, if one is planned (followSoon)
    infoInFlight: false,  // a GET maps/{id} for fitting is under way
    selectToken: 0,       // bumped on each map selection; late answers for an older one are ignored
    events: null,         // the EventSource of the selected map
    eventsBroken: false,  // the stream failed since it last opened: redraw everything when it reopens
    reconnectTimer: null,
    connection: 'starting',
    lastUpdate: null,     // Date of the last event received
    robots: new Map(),    // robot id -> {id, color, data, marker, trail, row, drawn, trailEdit}
    dirtyRobots: new Set(), // robots whose data changed since the last drawn frame
    listChanged: false,   // robots came or went since the last drawn frame: the list's rows change
    drawFrame: null,      // the requestAnimationFrame that draws what changed, if one is planned
    robotsSeen: 0,        // robots this map ever showed (the next robot's colour)
    tileCounter: 0,       // tile version counter (see the header comment)
    // Leaflet tile key -> {el, coords, loading, stale, reset, requestedAt, retryAt} for every tile on the map
    shownTiles: new Map(),
    pumpTimer: null,      // the next look for stale tiles that have become due
    pumpAt: Infinity,     // when pumpTimer fires (performance.now() time)
    pendingWindows: [],   // changed cell windows not yet redrawn
    pendingReset: false,  // redraw everything at the next flush
    flushTimer: null,
    lastFlush: 0,
    cellToken: 0,
    errorTimer: null,
    notFound: null,       // the map a #map= link named that does not exist (said once)
    viewChosen: false,    // the user moved the map (or a link named a view): the URL carries the view
    quietMove: false,     // the page itself is moving the map (fit, restore): not the user's choice
    pendingView: null,    // the view a link named for the map being selected ({x, y, z})
    cellSummary: '',      // the last cell query, in one sentence
  };

  // ---- small helpers ---------------------------------------------------------------------------

  const enc = encodeURIComponent;

  /**
   * Fetch JSON; throws an Error whose message is the service's error message when there is one. A 401
   * (the service needs a token to read, or the session's token was revoked) shows the sign-in form.
   */
  async function getJSON(url) {
    let resp;
    try {
      resp = await fetch(url, { headers: { Accept: 'application/json' }, cache: 'no-store' });
    } catch (err) {
      const e = new Error(`cannot reach the service (${err.message})`);
      e.network = true;
      throw e;
    }
    if (!resp.ok) {
      if (resp.status === 401) needSignIn();
      const err = new Error(`${url}: ${resp.status} ${await errorDetail(resp)}`);
      err.status = resp.status;
      throw err;
    }
    return resp.json();
  }

  /** The service's reason for an error answer (its JSON `detail`), else the status text. */
  async function errorDetail(resp) {
    try {
      const body = await resp.json();
      return typeof body.detail === 'string' ? body.detail : JSON.stringify(body.detail ?? body);
    } catch (_) {
      return resp.statusText; // not JSON
    }
  }

  /**
   * Show an error in the side panel (never thrown at the user); it fades after a while.
   * `network`: the message is about the service being unreachable; a reconnect clears it.
   */
  function showError(message, network = false) {
    // While the page asks for a token, what failed for want of one is no news (the form says it).
    if (!signInEl.hidden) return;
    errorEl.textContent = `${new Date().toLocaleTimeString()}: ${message}`;
    errorEl.hidden = false;
    errorEl.dataset.network = String(network);
    clearTimeout(state.errorTimer);
    state.errorTimer = setTimeout(() => { errorEl.hidden = true; }, ERROR_SHOW_MS);
  }

  /** The service answers again: a message saying it cannot be reached is no longer true. */
  function clearNetworkError() {
    if (!errorEl.hidden && errorEl.dataset.network === 'true') {
      clearTimeout(state.errorTimer);
      errorEl.hidden = true;
    }
  }

  /** An error the page said that is no longer true (e.g. the map a link named has appeared): hide it. */
  function clearError(message) {
    if (!errorEl.hidden && errorEl.textContent.endsWith(`: ${message}`)) {
      clearTimeout(state.errorTimer);
      errorEl.hidden = true;
    }
  }

  window.addEventListener('error', (e) => showError(e.message || String(e)));
  window.addEventListener('unhandledrejection', (e) => showError(String(e.reason && e.reason.message || e.reason)));

  /** The status line: connection state of the event stream and the time of the last update. */
  function setConnection(conn) {
    const was = state.connection;
    state.connection = conn;
    renderStatus();
    // Robots are online or offline only as far as a connected stream tells; else 'unknown'.
    if ((was === 'connected') !== (conn === 'connected')) redrawRobots();
  }

  function renderStatus() {
    const texts = {
      starting: 'starting…',
      waiting: 'waiting for robots…',
      connecting: 'connecting to events…',
      connected: 'connected',
      reconnecting: 'reconnecting to events…',
      error: 'event stream lost; retrying…',
      paused: 'paused while the tab is hidden',
      signin: 'sign in to see the maps',
    };
    // Two parts: the connection state is a live region (a screen reader says when it changes);
    // the time of the last update, which changes with nearly every event, is not.
    const text = texts[state.connection] || state.connection;
    if (statusTextEl.textContent !== text) statusTextEl.textContent = text;
    const last = state.lastUpdate && state.connection !== 'waiting'
      ? ` · last update ${state.lastUpdate.toLocaleTimeString()}` : '';
    // Equal text written again would still replace the text node and lay the toolbar out again.
    if (lastUpdateEl.textContent !== last) lastUpdateEl.textContent = last;
    if (statusEl.dataset.state !== state.connection) statusEl.dataset.state = state.connection;
  }

  // Robot ids in natural order: sim-2 before sim-10.
  const naturalOrder = new Intl.Collator(undefined, { numeric: true, sensitivity: 'base' });
  // Robot colours: saturated and dark enough to stand out on the light grey of free space.
  const ROBOT_COLORS = ['#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#e6550d',
    '#8c564b', '#d6339c', '#0f8b8d', '#4b4bb3', '#b8860b'];

  /**
   * The colour of the map's k-th robot (in the natural order of the ids first reported, so the same
   * robots get the same colours after a reload): the palette first, then hues a golden angle apart.
   * A hash of the id made robots share colours (with 12 robots, two pairs did), with no label to
   * tell them apart.
   */
  function robotColor(k) {
    if (k < ROBOT_COLORS.length) return ROBOT_COLORS[k];
    return `hsl(${Math.round(((k - ROBOT_COLORS.length) * 137.508 + 15) % 360)}, 70%, 38%)`;
  }

  /** Pose in any of the shapes the API may use ([x, y, theta] or {x, y, theta}) -> [x, y, theta] | null. */
  function normPose(p) {
    if (!p) return null;
    if (Array.isArray(p)) return p.length >= 2 ? [+p[0], +p[1], +(p[2] || 0)] : null;
    if (typeof p === 'object' && 'x' in p) return [+p.x, +p.y, +(p.theta || 0)];
    return null;
  }

  /** Metres -> Leaflet LatLng (lat = y / res, lng = x / res: one map unit per cell). */
  function toLatLng(x, y) {
    return L.latLng(y / state.res, x / state.res);
  }

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

  function fmt(v, key) {
    if (v === null || v === undefined || (typeof v === 'number' && Number.isNaN(v))) return '—';
    if (typeof v === 'boolean') return v ? 'yes' : 'no';
    if (typeof v === 'number') {
      if (key === 'hits' || key === 'misses' || Number.isInteger(v)) return String(v);
      return v.toFixed(key === 'probability' ? 4 : 3);
    }
    return String(v);
  }

  // ---- URL hash --------------------------------------------------------------------------------

  /** The hash's map, layer and view ({x, y, z}: centre in metres and zoom; null unless all three are
   * numbers, the centre within MAX_METRES, the zoom within the viewer's range). */
  function readHash() {
    const p = new URLSearchParams(location.hash.replace(/^#/, ''));
    const num = (k) => (p.get(k) === null || p.get(k).trim() === '' ? NaN : Number(p.get(k)));
    const [x, y, z] = [num('x'), num('y'), num('z')];
    const view = Math.abs(x) <= MAX_METRES && Math.abs(y) <= MAX_METRES
      && Number.isInteger(z) && z >= MIN_ZOOM && z <= MAX_ZOOM ? { x, y, z } : null;
    return { map: p.get('map'), layer: p.get('layer'), view };
  }

  /** The view shown, as the hash writes it: centre in metres (to the centimetre) and zoom. */
  function currentView() {
    const c = map.getCenter();
    return { x: +(c.lng * state.res).toFixed(2), y: +(c.lat * state.res).toFixed(2), z: map.getZoom() };
  }

  /** Replace (not push) the hash: switching maps or panning should not fill the back button's history. */
  function writeHash() {
    const p = new URLSearchParams();
    if (state.mapId) p.set('map', state.mapId);
    if (state.layer) p.set('layer', state.layer);
    if (state.mapId && state.viewChosen) {
      const v = currentView();
      p.set('x', String(v.x));
      p.set('y', String(v.y));
      p.set('z', String(v.z));
    }
    const hash = `#${p.toString()}`;
    if (location.hash !== hash) history.replaceState(null, '', hash);
  }

  /** Move the map without counting it as the user's choice of view (fitting, restoring a link). */
  function moveQuietly(move) {
    state.quietMove = true;
    try {
      move();
    } finally {
      state.quietMove = false;
    }
  }

  /** Show the view a link named: centre (metres) and zoom. */
  function showView(view) {
    moveQuietly(() => map.setView(toLatLng(view.x, view.y), view.z, { animate: false }));
  }

  /**
   * What the viewer has drawn since the page loaded, for tests and for the console: counts, never
   * timings. `frames`: animation frames that drew robots; `robotsDrawn`: robots drawn in them;
   * `trailsBuilt`: trails drawn from the whole trail (a new robot, a full `robots` event, a new
   * resolution); `trailsExtended`: trails that took only their new points; `rowsBuilt` / `rowsUpdated`:
   * robot-list rows made / rows whose text was rewritten.
   */
  const stats = {
    frames: 0, robotsDrawn: 0, trailsBuilt: 0, trailsExtended: 0, rowsBuilt: 0, rowsUpdated: 0,
  };
  window.__fleetmapViewerStats = stats;

  // ---- the Leaflet map -------------------------------------------------------------------------

  const map = L.map('map', {
    crs: L.CRS.Simple,
    minZoom: MIN_ZOOM,
    maxZoom: MAX_ZOOM,
    zoomSnap: 1,
    // Tiles are reloaded in place when the map changes; the fade-in would make them blink.
    fadeAnimation: false,
    center: [0, 0],
    zoom: 0,
  });
  map.attributionControl.setPrefix('Leaflet · fleetmap');

  /** The tile layer: its URL carries the map, the layer and the version counter. */
  const FleetTiles = L.TileLayer.extend({
    createTile(coords, done) {
      const img = L.TileLayer.prototype.createTile.call(this, coords, done);
      // Decode the PNG off the main thread; the tile shows its last image until the new one is ready.
      img.decoding = 'async';
      return img;
    },
    getTileUrl(coords) {
      const v = `${PAGE_STAMP}-${state.tileCounter}`;
      return `maps/${enc(state.mapId)}/tiles/${coords.z}/${coords.x}/${coords.y}.png` +
        `?layer=${enc(state.layer)}&v=${v}`;
    },
  });
  const tiles = new FleetTiles('', {
    tileSize: TILE_PX,
    minZoom: MIN_ZOOM,
    maxZoom: MAX_ZOOM,
    maxNativeZoom: MAX_ZOOM,
    minNativeZoom: MIN_ZOOM,
    noWrap: true,
    keepBuffer: 1,
    // A failed tile: a transparent image (unknown cells look the same), never the broken-image icon.
    errorTileUrl: 'data:image/gif;base64,R0lGODlhAQABAIAAAAAAAP///yH5BAEAAAAALAAAAAABAAEAAAIBRAA7',
  });
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
    e.tile.addEventListener('load', done);
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
      showError(`tile ${e.coords.z}/${e.coords.x}/${e.coords.y} failed to load`);
    }
  });

  // Trails stay SVG paths: one canvas for all of them (L.canvas) was measured dearer, since the whole
  // canvas bitmap (twice the view with Leaflet's padding) is handed to the compositor on every redraw
  // (docs/benchmarks.md, "Web viewer").
  const robotLayer = L.layerGroup().addTo(map);
  let cellMarker = null;

  map.on('mousemove', (e) => {
    const x = e.latlng.lng * state.res;
    const y = e.latlng.lat * state.res;
    coordsEl.textContent = `x ${x.toFixed(2)} m  y ${y.toFixed(2)} m`;
  });
  map.on('mouseout', () => { coordsEl.textContent = ''; });

  // A move the page did not make itself (a drag, the wheel, the keys, a robot row, a typed point) is
  // the user's choice of view; from then on the URL carries the view shown, for a link to it.
  map.on('movestart', () => { if (!state.quietMove && state.mapId) state.viewChosen = true; });
  map.on('moveend', () => { if (state.viewChosen && state.mapId) writeHash(); });

  // Leaflet measures its container only when told: whenever the map area changes size (window
  // resized, toolbar wrapping to another line, the folded panel opened under it), tell it, so the
  // view does not leave gaps. The centre stays where it was: it is the keyboard's cell cursor.
  if (window.ResizeObserver) {
    new ResizeObserver(() => map.invalidateSize({ pan: true, animate: false })).observe($('map'));
  }

  /** Forget the clicked cell (panel, outline, what was announced) and the cursor position. */
  function clearCell() {
    state.cellToken += 1; // an answer still on its way is for a cell no longer shown
    cellInfo.innerHTML = '<p class="none">Click the map, or type a point, to query a cell.</p>';
    delete cellInfo.dataset.i;
    delete cellInfo.dataset.j;
    if (cellMarker) { cellMarker.remove(); cellMarker = null; }
    coordsEl.textContent = '';
    cellAnnounce.textContent = '';
    state.cellSummary = '';
    renderSideSummary();
  }

  /** The folded panel's one line (narrow screens): the last cell queried, else the robots. */
  function renderSideSummary() {
    let text = state.cellSummary || '';
    if (!text && state.robots.size) {
      const online = [...state.robots.values()].filter((r) => robotState(r) === 'online').length;
      text = `${state.robots.size} robot${state.robots.size === 1 ? '' : 's'}, ${online} online`;
    }
    if (sideSummary.textContent !== text) sideSummary.textContent = text;
  }

  sideToggle.addEventListener('click', () => {
    const open = sideToggle.getAttribute('aria-expanded') !== 'true';
    sideToggle.setAttribute('aria-expanded', String(open));
    $('side').dataset.open = String(open);
  });

  /** The hint over a map with no scans yet: what to publish, and where. */
  function showNoScans(show) {
    if (show && state.mapId) {
      const v = document.createElement('var');
      v.textContent = 'ROBOT';
      noScansKey.replaceChildren(`fleetmap/${state.mapId}/`, v, '/scan');
    }
    noScansEl.hidden = !(show && state.mapId);
  }

  // ---- tile refresh ----------------------------------------------------------------------------

  /** The cell window [i0, j0, i1, j1) a tile covers (tile_render.tile_window without the step). */
  function tileCells(c) {
    const s = TILE_PX / Math.pow(2, c.z);
    return [c.x * s, -(c.y + 1) * s, (c.x + 1) * s, -c.y * s];
  }

  function intersects(a, b) {
    return a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
  }

  /** Whether the view shows the whole of a cell window [i0, j0, i1, j1]. */
  function windowInView(w) {
    return map.getBounds().contains(L.latLngBounds([w[1], w[0]], [w[3], w[2]]));
  }

  /** Whether the view shows the whole of the map's bounds [xmin, ymin, xmax, ymax] (metres). */
  function boundsInView(b) {
    return map.getBounds().contains(L.latLngBounds(toLatLng(b[0], b[1]), toLatLng(b[2], b[3])));
  }

  /** Queue changed windows (or a reset) and schedule one throttled flush. */
  function queueTiles(msg) {
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
    if (!state.mapId || !map.hasLayer(tiles)) return;
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

  // A stale tile that comes into view (pan, zoom) is due at once.
  map.on('moveend', () => schedulePump(0));

  // ---- robots ----------------------------------------------------------------------------------

  /** A robot's marker icon, made once per robot: an arrow pointing along +x (drawRobot turns it). */
  function robotIcon(color) {
    return L.divIcon({
      className: 'robot-marker',
      iconSize: [26, 26],
      iconAnchor: [13, 13],
      html: '<svg width="26" height="26" viewBox="-13 -13 26 26">' +
        `<circle r="6" fill="${color}" fill-opacity="0.35"/>` +
        `<path d="M12 0 L-7 -7 L-3 0 L-7 7 Z" fill="${color}" stroke="white" stroke-width="1.5"/></svg>`,
    });
  }

  /**
   * Merge robot reports ({id: {online, pose, trail, scans_integrated}}) and draw what changed.
   * `complete`: the reports are every robot of the map (a `robots` event), so a robot missing from
   * them was forgotten by the service (e.g. to make room on a full map) and is removed. `edits`: the
   * ids whose trail in `reports` is their known trail plus appended points (robots_delta), noted
   * in robot.trailEdit; any other trail is drawn whole. Drawing waits for the next frame.
   */
  function updateRobots(reports, complete = false, edits = null) {
    reports = reports || {};
    if (complete) {
      for (const id of [...state.robots.keys()]) {
        if (!(id in reports)) removeRobot(id);
      }
    }
    const ids = Object.keys(reports).sort(naturalOrder.compare);
    for (const id of ids) {
      const report = reports[id];
      let robot = state.robots.get(id);
      if (!robot) {
        const color = robotColor(state.robotsSeen);
        state.robotsSeen += 1;
        robot = {
          id,
          color,
          data: {},
          trail: L.polyline([], { color, weight: 2, opacity: 0.8, interactive: false }).addTo(robotLayer),
          marker: null,
          row: null,
          drawn: { marker: '', trail: '' }, // what marker and trail show now (see drawRobot)
          // Trail points appended and dropped since the trail was drawn ({add, drop}: robots_delta
          // events), false: draw it whole (other reports came), null: nothing yet (see drawTrail).
          trailEdit: false,
        };
        state.robots.set(id, robot);
        state.listChanged = true;
      }
      if (!edits || !edits.has(id)) robot.trailEdit = false; // drawn whole in the next frame
      Object.assign(robot.data, report);
      state.dirtyRobots.add(robot);
    }
    scheduleDraw();
  }

  /**
   * Draw what changed in the next animation frame, once however many events came in before it: a
   * robot that moved three times is drawn once, the list laid out once.
   */
  function scheduleDraw() {
    if (state.drawFrame === null) state.drawFrame = requestAnimationFrame(drawChanged);
  }

  function drawChanged() {
    state.drawFrame = null;
    if (!state.dirtyRobots.size && !state.listChanged) return;
    stats.frames += 1;
    const dirty = state.dirtyRobots;
    state.dirtyRobots = new Set();
    for (const robot of dirty) {
      if (state.robots.get(robot.id) !== robot) continue; // removed since
      drawRobot(robot);
      stats.robotsDrawn += 1;
    }
    renderRobotList(dirty);
  }

  /**
   * Apply a `robots_delta` event: the robots it removes go first (one forgotten and seen again under
   * its id is in both), then each robot it names takes its new fields, and its trail the appended
   * points, cut to the last `trail_length` (the service's RobotsEvent.apply does the same).
   */
  function applyRobotsDelta(delta) {
    for (const id of delta.removed || []) removeRobot(id);
    const reports = {};
    const edits = new Set();
    for (const [id, change] of Object.entries(delta.robots || {})) {
      const known = state.robots.get(id);
      const before = known && Array.isArray(known.data.trail) ? known.data.trail : [];
      const added = Array.isArray(change.trail) ? change.trail : [];
      const trail = before.concat(added);
      const drop = Math.max(0, trail.length - delta.trail_length);
      reports[id] = { ...change, trail: trail.slice(drop) };
      if (known && known.drawn.trail && known.trailEdit !== false) {
        // Its drawn trail can take the new points: edits add up until the next frame draws them.
        const edit = known.trailEdit || { add: [], drop: 0 };
        edit.add.push(...added);
        edit.drop += drop;
        known.trailEdit = edit;
        edits.add(id);
      }
    }
    updateRobots(reports, false, edits);
  }

  /** Take a robot off the map and out of the list. */
  function removeRobot(id) {
    const robot = state.robots.get(id);
    if (!robot) return;
    if (robot.marker) robot.marker.remove();
    robot.trail.remove();
    state.robots.delete(id);
    state.listChanged = true;
    scheduleDraw();
  }

  /**
   * What the page can say of a robot: 'online' / 'offline' as the service reports it, but 'unknown'
   * while the event stream is down (the service may be gone, and the robot with it).
   */
  function robotState(robot) {
    if (state.connection !== 'connected') return 'unknown';
    return robot.data.online ? 'online' : 'offline';
  }

  /**
   * Place a robot's marker and trail from its data. The marker's element is made once and then moved
   * and turned in place; neither is touched when what it shows did not change. `force`: draw again
   * even so (the resolution changed: the same metres are other map units).
   */
  function drawRobot(robot, force = false) {
    const id = robot.id;
    const pose = normPose(robot.data.pose ?? robot.data.last_pose);
    const shown = robotState(robot);
    const markerKey = pose ? `${pose.join(',')}:${shown}` : '';
    if (pose && (force || markerKey !== robot.drawn.marker)) {
      robot.drawn.marker = markerKey;
      const at = toLatLng(pose[0], pose[1]);
      if (!robot.marker) {
        robot.marker = L.marker(at, { icon: robotIcon(robot.color), keyboard: false, title: id })
          .addTo(robotLayer);
      } else {
        robot.marker.setLatLng(at);
      }
      const el = robot.marker.getElement();
      if (el) {
        // CSS rotates clockwise and the map's y axis points up, hence -theta.
        el.firstElementChild.style.transform = `rotate(${(-pose[2] * 180) / Math.PI}deg)`;
        el.classList.toggle('offline', shown !== 'online');
        el.dataset.robotId = id;
        el.dataset.online = shown === 'unknown' ? 'unknown' : String(shown === 'online');
      }
    }
    drawTrail(robot, pose, force);
  }

  /**
   * A robot's trail: its trail points, then its pose. A trail drawn before takes only its edit (the
   * points appended, the oldest dropped) in the polyline's own point array: old points are not
   * converted again, and the polyline and its SVG path stay the same objects.
   */
  function drawTrail(robot, pose, force) {
    const trail = Array.isArray(robot.data.trail) ? robot.data.trail : null;
    const edit = robot.trailEdit;
    robot.trailEdit = null;
    // The trail is a window of the last positions: its length and its ends say whether it moved.
    const trailKey = trail && `${trail.length}:${trail[0]}:${trail[trail.length - 1]}:${pose}`;
    if (!trail || (!force && trailKey === robot.drawn.trail)) return;
    const wasDrawn = robot.drawn.trail;
    robot.drawn.trail = trailKey;
    const added = edit && edit.add.map((p) => normPose(p));
    if (!force && edit && wasDrawn && added.every(Boolean)) {
      const points = robot.trail.getLatLngs();
      if (robot.drawn.posePoint) points.pop();
      for (const p of added) points.push(toLatLng(p[0], p[1]));
      points.splice(0, Math.min(edit.drop, points.length));
      if (pose) points.push(toLatLng(pose[0], pose[1]));
      robot.drawn.posePoint = !!pose;
      robot.trail.setLatLngs(points); // the same LatLng objects: only their bounds are gathered again
      stats.trailsExtended += 1;
      return;
    }
    const points = trail.map((p) => normPose(p)).filter(Boolean).map((p) => toLatLng(p[0], p[1]));
    if (pose) points.push(toLatLng(pose[0], pose[1]));
    robot.drawn.posePoint = !!pose;
    robot.trail.setLatLngs(points);
    stats.trailsBuilt += 1;
  }

  /** Redraw every robot (the connection state or the resolution changed). */
  function redrawRobots() {
    for (const robot of state.robots.values()) drawRobot(robot, true);
    renderRobotList(state.robots.values());
  }

  /** Centre the map on a robot (its row was clicked, or Enter / Space pressed on it). */
  function centreOnRobot(id) {
    const robot = state.robots.get(id);
    if (robot && robot.marker) map.panTo(robot.marker.getLatLng());
  }

  /** A robot's row: a button (focusable with Tab, Enter / Space centre the map on the robot). */
  function robotRow(robot) {
    const li = document.createElement('li');
    li.dataset.robotId = robot.id;
    const button = document.createElement('button');
    button.type = 'button';
    button.className = 'robot';
    button.title = 'Centre the map on this robot';
    const swatch = document.createElement('span');
    swatch.className = 'swatch';
    swatch.style.background = robot.color;
    const name = document.createElement('span');
    name.className = 'name';
    name.textContent = robot.id;
    const st = document.createElement('span');
    st.className = 'online-state';
    const scans = document.createElement('span');
    scans.className = 'scans';
    button.append(swatch, name, st, scans);
    button.addEventListener('click', () => centreOnRobot(robot.id));
    li.append(button);
    return li;
  }

  /**
   * The robot list. Rows are updated in place, keyed by robot id: robots events come several times
   * a second, and a row rebuilt between the press and the release of a click would lose the click.
   */
  function renderRobotList(changed) {
    const count = state.robots.size ? `(${state.robots.size})` : '';
    if (robotCount.textContent !== count) robotCount.textContent = count;
    renderSideSummary();
    if (state.robots.size === 0) {
      if (!robotList.querySelector('li.none')) {
        const li = document.createElement('li');
        li.className = 'none';
        li.textContent = 'no robots';
        robotList.replaceChildren(li);
      }
      return;
    }
    for (const robot of changed) {
      if (state.robots.get(robot.id) !== robot) continue; // removed since
      if (!robot.row) {
        robot.row = robotRow(robot);
        stats.rowsBuilt += 1;
      }
      if (renderRow(robot)) stats.rowsUpdated += 1;
    }
    if (!state.listChanged && robotList.children.length === state.robots.size) return;
    state.listChanged = false;
    // Rows join or leave the list only when robots come or go, in their order.
    const ids = [...state.robots.keys()].sort(naturalOrder.compare);
    const rows = ids.map((id) => state.robots.get(id).row).filter(Boolean);
    const current = [...robotList.children];
    if (current.length !== rows.length || current.some((el, k) => el !== rows[k])) {
      robotList.replaceChildren(...rows);
    }
  }

  /** Write a robot's state and scan count into its row, where they changed; true if any did. */
  function renderRow(robot) {
    const shown = robotState(robot);
    const li = robot.row;
    const online = shown === 'unknown' ? 'unknown' : String(shown === 'online');
    const scans = `${robot.data.scans_integrated ?? 0} scans`;
    const st = li.children[0].children[2]; // button > .online-state (see robotRow)
    const scansEl = li.children[0].children[3]; // button > .scans
    if (li.dataset.online === online && st.textContent === shown && scansEl.textContent === scans) return false;
    li.dataset.online = online;
    if (st.textContent !== shown) st.textContent = shown;
    if (scansEl.textContent !== scans) scansEl.textContent = scans;
    return true;
  }

  function clearRobots() {
    robotLayer.clearLayers();
    state.robots.clear();
    state.dirtyRobots.clear();
    state.robotsSeen = 0;
    state.listChanged = true;
    renderRobotList([]);
  }

  // ---- cell query ----------------------------------------------------------------------------

  map.on('click', (e) => queryCell(Math.floor(e.latlng.lng), Math.floor(e.latlng.lat)));

  // Without a mouse: with the map focused (Tab), arrow keys pan and + / - zoom (Leaflet's keyboard
  // handler), and Enter queries the cell under the cross at the centre. Enter on a zoom button inside
  // the map is that button's.
  map.getContainer().addEventListener('keydown', (e) => {
    if (e.key !== 'Enter' || e.target !== map.getContainer()) return;
    e.preventDefault();
    const c = map.getCenter();
    queryCell(Math.floor(c.lng), Math.floor(c.lat));
  });

  /** A typed coordinate in metres, or null with the reason shown next to the form. */
  function typedMetres(input, name) {
    const text = input.value.trim();
    const v = text === '' ? NaN : Number(text);
    // A number input gives '' for text that is not a number: say what is wrong either way.
    if (!(Math.abs(v) <= MAX_METRES) || (input.validity && input.validity.badInput)) {
      input.setAttribute('aria-invalid', 'true');
      cellFormError.textContent = `${name}: enter a number of metres between -${MAX_METRES} and ${MAX_METRES}`;
      cellFormError.hidden = false;
      input.focus();
      return null;
    }
    input.removeAttribute('aria-invalid');
    return v;
  }

  // A typed point: the map moves there and its cell is queried, as a click there would.
  cellForm.addEventListener('submit', (e) => {
    e.preventDefault();
    const x = typedMetres(cellX, 'x');
    if (x === null) return;
    const y = typedMetres(cellY, 'y');
    if (y === null) return;
    cellFormError.hidden = true;
    if (!state.mapId) {
      cellFormError.textContent = 'there is no map to query';
      cellFormError.hidden = false;
      return;
    }
    map.panTo(toLatLng(x, y));
    queryCell(Math.floor(x / state.res), Math.floor(y / state.res), [x, y]);
  });

  /** The outline of cell (i, j), and a ring of fixed screen size so it can be found at any zoom. */
  function drawCellMarker(i, j) {
    if (cellMarker) cellMarker.remove();
    cellMarker = L.featureGroup([
      L.rectangle([[j, i], [j + 1, i + 1]], { color: '#0969da', weight: 2, fill: false, interactive: false }),
      L.circleMarker([j + 0.5, i + 0.5], { radius: 9, color: '#0969da', weight: 2, fill: false, interactive: false }),
    ]).addTo(map);
  }

  /**
   * Ask for cell (i, j) and show its values. `point`: the [x, y] in metres to ask at (a typed point);
   * by default the cell's centre (no rounding doubts at cell edges).
   */
  async function queryCell(i, j, point = null) {
    if (!state.mapId) return;
    const token = ++state.cellToken;
    const [x, y] = point || [(i + 0.5) * state.res, (j + 0.5) * state.res];
    drawCellMarker(i, j);
    cellInfo.innerHTML = '<p class="none">querying…</p>';
    try {
      const cell = await getJSON(`maps/${enc(state.mapId)}/cell?x=${x}&y=${y}`);
      if (token !== state.cellToken) return;
      // The service says which cell it answered for (i, j); trust it over our own arithmetic.
      const ci = Number.isInteger(cell.i) ? cell.i : i;
      const cj = Number.isInteger(cell.j) ? cell.j : j;
      if (ci !== i || cj !== j) drawCellMarker(ci, cj);
      renderCell(ci, cj, x, y, cell);
      if (!point) {
        cellX.value = String(+x.toFixed(3));
        cellY.value = String(+y.toFixed(3));
      }
    } catch (err) {
      if (token !== state.cellToken) return;
      cellInfo.innerHTML = '<p class="none">no value</p>';
      announceCell(`cell query failed: ${err.message}`);
      showError(`cell query: ${err.message}`, !!err.network);
    }
  }

  /** One sentence for the live region and the folded panel's line. */
  function announceCell(text) {
    cellAnnounce.textContent = text;
    state.cellSummary = text;
    renderSideSummary();
  }

  /** What a cell holds, in words: its state and probability, its counts, its TSDF value. */
  function cellSentence(i, j, x, y, cell) {
    const parts = [];
    if ('state' in cell) parts.push(String(cell.state));
    if ('probability' in cell && cell.known) parts.push(`probability ${fmt(cell.probability, 'probability')}`);
    if ('hits' in cell) parts.push(`${fmt(cell.hits, 'hits')} hits, ${fmt(cell.misses, 'misses')} misses`);
    if (!('state' in cell) && 'tsdf' in cell) parts.push(`TSDF ${fmt(cell.tsdf, 'tsdf')}`);
    return `Cell (${i}, ${j}) at x ${x.toFixed(2)} m, y ${y.toFixed(2)} m: ${parts.join(', ')}`;
  }

  function renderCell(i, j, x, y, cell) {
    const where = document.createElement('p');
    where.className = 'where';
    where.textContent = `cell (${i}, ${j}) · x ${x.toFixed(3)} m, y ${y.toFixed(3)} m`;
    const table = document.createElement('table');
    for (const key of CELL_FIELDS) {
      if (!(key in cell)) continue; // a layer the map does not keep
      const tr = document.createElement('tr');
      const th = document.createElement('th');
      th.textContent = key;
      const td = document.createElement('td');
      td.dataset.field = key;
      td.textContent = fmt(cell[key], key);
      if (key === 'state') td.dataset.state = String(cell[key]);
      tr.append(th, td);
      table.append(tr);
    }
    cellInfo.replaceChildren(where, table);
    cellInfo.dataset.i = String(i);
    cellInfo.dataset.j = String(j);
    announceCell(cellSentence(i, j, x, y, cell));
  }

  // ---- event stream ----------------------------------------------------------------------------

  function closeEvents() {
    clearTimeout(state.reconnectTimer);
    state.reconnectTimer = null;
    if (state.events) state.events.close();
    state.events = null;
  }

  function openEvents(mapId) {
    closeEvents();
    if (document.visibilityState === 'hidden') {
      // Nobody looks: no stream until the tab is shown (see the visibilitychange listener).
      setConnection('paused');
      return;
    }
    setConnection('connecting');
    const es = new EventSource(`maps/${enc(mapId)}/events?robots=delta`);
    state.events = es;
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
      state.lastUpdate = new Date();
      renderStatus();
      fn(data);
    };
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

  // ---- maps and layers -------------------------------------------------------------------------

  /** Poll the map list; keep the selection, pick one when there is none. */
  async function refreshMaps() {
    if (!signInEl.hidden) return; // refused until the user signs in (the form asks again then)
    let ids;
    try {
      const body = await getJSON('maps');
      const items = Array.isArray(body) ? body : (body.maps || []);
      ids = items.map((m) => (typeof m === 'string' ? m : m.id)).filter(Boolean).sort();
    } catch (err) {
      showError(`map list: ${err.message}`, !!err.network);
      return;
    }
    const current = [...mapSelect.options].map((o) => o.value);
    if (ids.join('\n') !== current.join('\n')) setMapOptions(ids);
    mapSelect.disabled = ids.length === 0;
    emptyEl.hidden = ids.length > 0;
    if (ids.length === 0) {
      if (state.mapId) deselectMap();
      setConnection('waiting');
      // A link to a map that does not exist (yet): say so once; it is shown as soon as it appears.
      const wanted = readHash().map;
      if (wanted && state.notFound !== wanted) showError(`map ${wanted} not found`);
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
  function setMapOptions(ids) {
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
  function deselectMap(keepHash = false) {
    state.selectToken += 1; // answers still on their way are for a map no longer shown
    state.mapId = null;
    state.info = null;
    state.viewChosen = false;
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
  async function selectMap(mapId) {
    const token = ++state.selectToken;
    closeEvents();
    clearRobots();
    state.mapId = mapId;
    state.info = null;
    state.fitted = false;
    state.eventsBroken = false;
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
    openEvents(mapId);
  }

  /**
   * The selected map was replaced under its id: its configuration (layers, resolution), cells and
   * robots are new. Forget what the page knew of the old one and load it again, as a selection does,
   * but keep the event stream (it goes on with the new map) and the map selector as they are.
   * `spread`: reload the tiles after a random delay of up to RECONNECT_SPREAD_MS (after a reconnect).
   */
  async function reloadMap(refit = true, spread = false) {
    const token = state.selectToken;
    clearRobots();
    // A replaced map may lie elsewhere; after a reconnect keep the user's view unless the
    // resolution changed (refreshInfo refits then: the same cell indices are other places).
    if (refit) state.fitted = false;
    clearCell();
    await refreshInfo(token, true);
    // Every tile, after the layer selector knows the new map's layers (the layer may have changed).
    const reset = () => { if (token === state.selectToken) queueTiles({ reset: true }); };
    if (spread) setTimeout(reset, Math.random() * RECONNECT_SPREAD_MS);
    else reset();
  }

  /** GET maps/{id}: layers, resolution, bounds (fitted, and again as the map grows until the user
   * moves it), robots. Returns false on failure. */
  async function refreshInfo(token, first) {
    const mapId = state.mapId;
    let info;
    try {
      info = await getJSON(`maps/${enc(mapId)}`);
    } catch (err) {
      showError(`map ${mapId}: ${err.message}`, !!err.network);
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
        const reports = {};
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

  /** Fill the layer selector with the tile layers this map keeps; keep the wanted one if possible. */
  function setLayerOptions(mapLayers) {
    const kept = Array.isArray(mapLayers) ? mapLayers : ['occupancy', 'counts', 'tsdf'];
    const available = LAYERS.filter((l) => kept.includes(l.needs));
    layerSelect.replaceChildren(...available.map((l) => {
      const o = document.createElement('option');
      o.value = l.name;
      o.textContent = l.label;
      return o;
    }));
    layerSelect.disabled = available.length === 0;
    const names = available.map((l) => l.name);
    const wanted = readHash().layer || state.layer;
    state.layer = names.includes(wanted) ? wanted : (names[0] || null);
    // A link (or the layer shown before) named a layer this map does not keep: say which is shown.
    if (wanted && state.layer && wanted !== state.layer) {
      showError(`map ${state.mapId} has no ${wanted} layer (it keeps ${kept.join(', ')}): showing ${state.layer}`);
    }
    if (state.layer) layerSelect.value = state.layer;
    writeHash();
  }

  mapSelect.addEventListener('change', () => {
    if (mapSelect.value && mapSelect.value !== state.mapId) selectMap(mapSelect.value);
  });

  layerSelect.addEventListener('change', () => {
    state.layer = layerSelect.value;
    writeHash();
    state.tileCounter += 1;
    if (map.hasLayer(tiles)) tiles.redraw();
  });

  // Someone edited the hash (or followed a link): apply it.
  window.addEventListener('hashchange', async () => {
    const h = readHash();
    const known = () => [...mapSelect.options].some((o) => o.value === h.map);
    if (h.map && h.map !== state.mapId) {
      if (!known()) await refreshMaps(); // the map list is polled: it may be new
      if (h.map !== readHash().map || h.map === state.mapId) return; // edited again meanwhile
      if (known()) {
        selectMap(h.map);
      } else {
        showError(`map ${h.map} not found`);
        if (state.mapId) writeHash(); // back to the map shown
      }
      return;
    }
    if (!state.mapId) return;
    if (h.layer && h.layer !== state.layer) {
      if ([...layerSelect.options].some((o) => o.value === h.layer)) {
        layerSelect.value = h.layer;
        layerSelect.dispatchEvent(new Event('change'));
      } else {
        showError(`map ${state.mapId} has no ${h.layer} layer: showing ${state.layer}`);
        writeHash(); // the URL names the layer shown
      }
    }
    const v = currentView();
    if (h.view && (h.view.x !== v.x || h.view.y !== v.y || h.view.z !== v.z)) {
      state.viewChosen = true;
      showView(h.view);
    }
  });

  // ---- signing in -------------------------------------------------------------------------------

  /**
   * A read was refused for want of a valid token: nothing of the maps stays on the page (its user
   * may no longer see them; the URL keeps the map and view, shown again after signing in), and the
   * sign-in form takes the map's place.
   */
  function needSignIn() {
    if (!signInEl.hidden) return;
    deselectMap(true);
    setMapOptions([]);
    mapSelect.disabled = true;
    emptyEl.hidden = true;
    clearTimeout(state.errorTimer);
    errorEl.hidden = true;
    rememberSignedIn(false);
    signInError.hidden = true;
    signInEl.hidden = false;
    setConnection('signin');
    signInToken.focus();
  }

  /** Say why signing in failed, under the form's button (an alert: a screen reader says it). */
  function signInFailed(message) {
    signInError.textContent = message;
    signInError.hidden = false;
    signInToken.setAttribute('aria-invalid', 'true');
    signInToken.focus();
  }

  /** Whether this browser holds a session: shows "Sign out" (kept over reloads, see SIGNED_IN_KEY). */
  function rememberSignedIn(signedIn) {
    signOutButton.hidden = !signedIn;
    try {
      if (signedIn) localStorage.setItem(SIGNED_IN_KEY, '1');
      else localStorage.removeItem(SIGNED_IN_KEY);
    } catch (_) { /* storage blocked: "Sign out" shows until the page is reloaded */ }
  }

  // The token goes to the service once, in a header; the page forgets it as soon as it is sent.
  signInForm.addEventListener('submit', async (e) => {
    e.preventDefault();
    const token = signInToken.value.trim();
    if (!TOKEN_CHARS.test(token)) {
      signInFailed(token ? 'a token holds printable ASCII characters only, no spaces' : 'enter your API token');
      return;
    }
    let resp;
    try {
      resp = await fetch('session', {
        method: 'POST',
        headers: { Authorization: `Bearer ${token}`, Accept: 'application/json' },
        cache: 'no-store',
      });
    } catch (err) {
      signInFailed(`cannot reach the service (${err.message})`);
      return;
    }
    if (!resp.ok) {
      signInFailed(resp.status === 401 ? 'unknown token: check it and try again'
        : `cannot sign in: ${resp.status} ${await errorDetail(resp)}`);
      return;
    }
    signInToken.value = '';
    signInToken.removeAttribute('aria-invalid');
    signInError.hidden = true;
    signInEl.hidden = true;
    rememberSignedIn(true);
    setConnection('starting');
    refreshMaps();
  });

  // Signing out clears the cookie; the next request then shows the form (or, if reads are open after
  // all, the page goes on as it is).
  signOutButton.addEventListener('click', async () => {
    rememberSignedIn(false);
    try {
      await fetch('session', { method: 'DELETE', cache: 'no-store' });
    } catch (err) {
      showError(`cannot sign out: cannot reach the service (${err.message})`, true);
      return;
    }
    refreshMaps();
  });

  // Clicks, drags and the wheel over the form are the form's, not the map's under it.
  L.DomEvent.disableClickPropagation(signInEl);
  L.DomEvent.disableScrollPropagation(signInEl);

  // ---- start -----------------------------------------------------------------------------------

  renderStatus();
  try {
    signOutButton.hidden = localStorage.getItem(SIGNED_IN_KEY) !== '1';
  } catch (_) { /* storage blocked: no "Sign out" until the user signs in on this page */ }
  refreshMaps();
  setInterval(refreshMaps, MAPS_REFRESH_MS);

  // For tests and debugging from the console: read-only views of the viewer's state.
  window.fleetmapViewer = { map, tiles, state };
})();
