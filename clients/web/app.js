/*
 * fleetmap web viewer: plain JavaScript on Leaflet, no build step.
 *
 * What it shows and where it gets it (all URLs relative to the page, so a path prefix works):
 *   GET maps                      -> the map selector (refreshed every MAPS_REFRESH_MS while shown)
 *   GET maps/{id}                 -> config.layers (layer selector), config.resolution, stats.bounds (fit),
 *                                    stats.robots (initial robot list)
 *   GET maps/{id}/tiles/{z}/{x}/{y}.png?layer=L&v=V
 *                                 -> the map itself on L.CRS.Simple: one map unit = one CELL,
 *                                    lng = cell x index i, lat = cell y index j, zoom 0 = one pixel per cell
 *   GET maps/{id}/events?robots=delta&keepalive=event[&since=stats.version] (SSE; `since` on a
 *                                    map's first stream: its version when read, before its tiles)
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
 * change, and whenever a map is selected (one shown before may have changed meanwhile). A displayed
 * tile whose cells intersect a changed window is marked stale, and a stale tile gets a new URL (so a
 * new request, never a stale browser-cache hit) only when (a) it is in view, (b) its previous request
 * has finished, (c) TILE_REFRESH_MS have passed since that request began, (d) the page is visible,
 * and (e) the map's layers are known (not while a replaced or reconnected map's GET is under way:
 * the layer shown may be one it no longer keeps; a failed one is asked again every MAP_RETRY_MS). So a tile that changes 50 times a second is
 * fetched at most 1000 / TILE_REFRESH_MS times a second, a slow service is never asked for a tile it
 * is still rendering, and a hidden tab fetches nothing (it also closes its event stream until shown
 * again).
 * Tiles created later use the newest counter; while (e) does not hold, they show nothing until it does
 * (the user panned or zoomed while a replaced map loads: asked for at once, they were refused 422).
 * A tile that failed to load is stale again, due TILE_RETRY_MS later (while the event stream is
 * connected; a reconnect reloads every tile anyway).
 * The stream's keepalive events (every 15 s of silence by default) bound its silences: one silent
 * for SILENT_STREAM_INTERVALS of them is opened again (events.js), as after any break.
 *
 * Signing in: a service run with --require-read-token answers every read 401 without a token, and
 * neither an <img> tile nor an EventSource can send one. A 401 shows a form (over the map) whose token
 * is posted once to `session` in an Authorization header; the service answers with a session cookie
 * (HttpOnly: this page never sees it) that the browser then sends with every request, tiles and the
 * event stream included. The page keeps no token. A 401 later (the token was revoked) shows the form
 * again, saying the session ended; with reads open no request is ever refused, and the page never
 * shows it (a form shown before the service restarted with reads open goes on to the maps when
 * its sign-in is refused, as a read then works).
 *
 * Robots are drawn incrementally: a robot's marker and trail are made once, then moved and turned in
 * place, and only when its report changed; a robot the service no longer reports is removed. The
 * stream sends only the robots that changed and their new trail points (`robots_delta`), so 100
 * robots moving at 2 Hz cost ~30 kB a second instead of 0.5 to 1.5 MB.
 *
 * The viewer is native ES modules (index.html loads this one with <script type="module">, which
 * imports the rest; Leaflet's leaflet.js, a classic script loaded before it, is the global `L`):
 *   app.js          wires the modules together and starts the viewer (this file)
 *   config.js       settings: tile geometry, zoom range, refresh and retry timings, stored keys
 *   state.js        what the viewer knows and is doing (`state`), what it has drawn (`stats`)
 *   dom.js          the page's elements, looked up once
 *   rest.js         JSON reads from the service (getJSON) and the reasons of its error answers
 *   signin.js       the sign-in form and "Sign out" (below)
 *   status.js       the status line and the side panel's error messages
 *   leaflet-map.js  the Leaflet map, metres -> map units, moves the page makes itself
 *   hash.js         the URL hash: map, layer and view
 *   maps.js         the map selector, selecting a map, its metadata and fitting the view to it
 *   layers.js       the layer selector
 *   tiles.js        the live tile layer and its refresh rules (below)
 *   robots.js       the robots on the map: markers and trails from robots / robots_delta (below)
 *   robot-list.js   the robot list in the side panel
 *   side-panel.js   the side panel folded on a narrow screen, and its one line of summary
 *   cell.js         the cell inspector: click, Enter or a typed point -> the cell's values
 *   events.js       the event stream, its reconnects, and pausing it while the tab is hidden
 * The modules call one another's functions freely (some in a circle: selecting a map opens its event
 * stream, whose events load the map again). Loading one only defines its names (and looks up the
 * page's elements); nothing happens until app.js calls each part's wiring below, in the order they
 * ran in when the viewer was one script.
 */
import { queryCellsOnInput } from './cell.js';
import { MAPS_REFRESH_MS } from './config.js';
import { pauseWhileHidden } from './events.js';
import { followHashEdits, trackChosenView } from './hash.js';
import { switchLayerOnChange } from './layers.js';
import { createMap, followContainerSize, map, showPointerCoords } from './leaflet-map.js';
import { refreshMaps, selectMapOnChange } from './maps.js';
import { addRobotLayer } from './robots.js';
import { toggleSidePanelOnClick } from './side-panel.js';
import { handleSignInAndOut, showSignOutIfSignedIn } from './signin.js';
import { state, stats } from './state.js';
import { renderStatus, reportUncaughtErrors } from './status.js';
import { tiles, trackShownTiles } from './tiles.js';

// ---- wiring ------------------------------------------------------------------------------------

reportUncaughtErrors();
window.__fleetmapViewerStats = stats;
createMap();
addRobotLayer();
showPointerCoords();
trackChosenView();
followContainerSize();
trackShownTiles();
toggleSidePanelOnClick();
queryCellsOnInput();
pauseWhileHidden();
selectMapOnChange();
switchLayerOnChange();
followHashEdits();
handleSignInAndOut();

// ---- start -------------------------------------------------------------------------------------

renderStatus();
showSignOutIfSignedIn();
refreshMaps();
// Not while the tab is hidden, which shows nothing and so asks for nothing (pauseWhileHidden); once
// shown, at once, as its stream catches up.
setInterval(() => { if (document.visibilityState !== 'hidden') refreshMaps(); }, MAPS_REFRESH_MS);
document.addEventListener('visibilitychange', () => {
  if (document.visibilityState !== 'hidden') refreshMaps();
});

// For tests and debugging from the console: read-only views of the viewer's state.
window.fleetmapViewer = { map, tiles, state };
