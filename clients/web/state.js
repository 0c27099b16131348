/*
 * What the viewer knows and is doing, in one place: `state` (the selected map and layer, the event
 * stream, the robots, the tiles on the map and their refresh timers, the view) and `stats` (what it
 * has drawn). Every module reads and writes these two objects; nothing else holds the viewer's state
 * (the Leaflet map and tile layer are objects of their own: leaflet-map.js, tiles.js). app.js hands
 * both to the page as window.fleetmapViewer.state and window.__fleetmapViewerStats, for tests and the
 * console.
 */
export const state = {
  mapId: null,          // selected map id
  layer: null,          // selected tile layer name
  info: null,           // last GET maps/{id} answer
  res: 0.05,            // metres per cell of the selected map
  fitted: false,        // view fitted to the map's bounds (again as it grows, until the user moves it)
  followedAt: -Infinity, // when the bounds were last looked up to follow the growing map
  followTimer: null,    // the next such look, if one is planned (followSoon)
  infoInFlight: false,  // a GET maps/{id} for fitting is under way
  selectToken: 0,       // bumped on each map selection; late answers for an older one are ignored
  reloads: 0,           // reloads of the selected map begun (reloadMap)
  tilesHeldBy: 0,       // the reload whose GET of the map holds tile requests back (its layers unknown), or 0
  events: null,         // the EventSource of the selected map
  eventsBroken: false,  // the stream failed since it last opened: redraw everything when it reopens
  reconnectTimer: null,
  silenceTimer: null,   // fires when the open stream has been silent too long (events.js)
  connection: 'starting',
  lastUpdate: null,     // Date of the last event received
  robots: new Map(),    // robot id -> {id, color, data, marker, trail, row, drawn, trailEdit}
  dirtyRobots: new Set(), // robots whose data changed since the last drawn frame
  listChanged: false,   // robots came or went since the last drawn frame: the list's rows change
  drawFrame: null,      // the requestAnimationFrame that draws what changed, if one is planned
  robotsSeen: 0,        // robots this map ever showed (the next robot's colour)
  tileCounter: 0,       // tile version counter (see the app.js header)
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
  cellMarker: null,     // the queried cell's outline on the map (cell.js), if one is shown
  cellShown: null,      // the cell shown in the panel, {i, j, point}: asked again when it changes
};

/**
 * What the viewer has drawn since the page loaded, for tests and for the console: counts, never
 * timings. `frames`: animation frames that drew robots; `robotsDrawn`: robots drawn in them;
 * `trailsBuilt`: trails drawn from the whole trail (a new robot, a full `robots` event, a new
 * resolution); `trailsExtended`: trails that took only their new points; `rowsBuilt` / `rowsUpdated`:
 * robot-list rows made / rows whose text was rewritten.
 */
export const stats = {
  frames: 0, robotsDrawn: 0, trailsBuilt: 0, trailsExtended: 0, rowsBuilt: 0, rowsUpdated: 0,
};
