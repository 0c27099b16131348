/*
 * The viewer's settings: tile geometry, zoom range, refresh and retry timings, and the keys it
 * keeps. Constants only, read by the other modules; the app.js header says how the timings work
 * together (live refresh, reconnects).
 */
export const TILE_PX = 256;            // tile size in pixels (the service's tile_render.TILE_PX)
export const MIN_ZOOM = -8;            // 256 cells per pixel
export const MAX_ZOOM = 4;             // 16 pixels per cell; the service renders zooms -8..4
// The farthest point (metres from the origin, on x and on y) a typed point or a link's view may
// name. Farther, Leaflet's pixel arithmetic fails: 1e308 m is an infinite number of cells (it
// threw, and the map was never shown), 1e16 m at zoom 4 asked for so many tiles that the tab died.
export const MAX_METRES = 1e7;
export const MAPS_REFRESH_MS = 5000;   // how often the map list is polled
export const TILE_FLUSH_MS = 100;      // changed windows are applied to the tiles at most this often
export const TILE_REFRESH_MS = 500;    // one tile is requested again at most this often (2 per second)
export const TILE_RETRY_MS = 3000;     // a tile that failed to load is asked for again after this long
export const RECONNECT_MS = 3000;      // retry delay when the browser gives up on the event stream
export const MAP_RETRY_MS = 3000;      // a replaced map's GET that failed is asked again after this long
export const MAX_RETRY_AFTER_MS = 60000; // the longest a refusal's Retry-After holds the stream's retry back
// The event stream sends a `keepalive` event after every `interval` seconds without news (it says
// how many when it opens): one that sent nothing for this many intervals died without a word (a
// half-open connection: a NAT or proxy dropped it, the laptop slept), and is opened again.
export const SILENT_STREAM_INTERVALS = 3;
// Until the user moves the map, the view follows the map as it grows (a demo's robots explore
// beyond the first fit): its bounds are looked up at most this often while tiles change.
export const FOLLOW_MS = 2000;
// After a reconnect every tile is reloaded once; spread over this many ms, so that the viewers of a
// restarted service do not all ask it for their tiles in the same instant.
export const RECONNECT_SPREAD_MS = 1000;
export const ERROR_SHOW_MS = 15000;    // how long an error message stays visible
// localStorage key set while this browser holds a session (so a reloaded page offers "Sign out":
// the cookie itself is HttpOnly, out of the page's reach).
export const SIGNED_IN_KEY = 'fleetmap.signedIn';
// What a token may hold (fleetmap.auth): printable ASCII, no space.
export const TOKEN_CHARS = /^[\x21-\x7e]+$/;
