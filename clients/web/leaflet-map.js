/*
 * The Leaflet map (`map`, made by createMap) on L.CRS.Simple: one map unit is one cell, lng = cell x
 * index i, lat = cell y index j, zoom 0 = one pixel per cell. toLatLng turns metres into map units at
 * the selected map's resolution (state.res). Moves the page makes itself (fitting, a link's view) go
 * through moveQuietly, so that they do not count as the user's choice of view (hash.js). Also here:
 * the pointer's coordinates under the map, and telling Leaflet when its container changes size.
 */
import { MAX_ZOOM, MIN_ZOOM } from './config.js';
import { $, coordsEl } from './dom.js';
import { state } from './state.js';

/** The Leaflet map; null until createMap. */
export let map = null;

/** Make the Leaflet map in the page's #map element. */
export function createMap() {
  map = L.map('map', {
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
}

/** Metres -> Leaflet LatLng (lat = y / res, lng = x / res: one map unit per cell). */
export function toLatLng(x, y) {
  return L.latLng(y / state.res, x / state.res);
}

/** Move the map without counting it as the user's choice of view (fitting, restoring a link). */
export function moveQuietly(move) {
  state.quietMove = true;
  try {
    move();
  } finally {
    state.quietMove = false;
  }
}

/** Show the view a link named: centre (metres) and zoom. */
export function showView(view) {
  moveQuietly(() => map.setView(toLatLng(view.x, view.y), view.z, { animate: false }));
}

/** Whether the view shows the whole of a cell window [i0, j0, i1, j1]. */
export function windowInView(w) {
  return map.getBounds().contains(L.latLngBounds([w[1], w[0]], [w[3], w[2]]));
}

/** Whether the view shows the whole of the map's bounds [xmin, ymin, xmax, ymax] (metres). */
export function boundsInView(b) {
  return map.getBounds().contains(L.latLngBounds(toLatLng(b[0], b[1]), toLatLng(b[2], b[3])));
}

/** Show the pointer's position under the map, in metres (#coords). */
export function showPointerCoords() {
  map.on('mousemove', (e) => {
    const x = e.latlng.lng * state.res;
    const y = e.latlng.lat * state.res;
    coordsEl.textContent = `x ${x.toFixed(2)} m  y ${y.toFixed(2)} m`;
  });
  map.on('mouseout', () => { coordsEl.textContent = ''; });
}

/** Keep Leaflet's idea of its container's size true. */
export function followContainerSize() {
  // Leaflet measures its container only when told: whenever the map area changes size (window
  // resized, toolbar wrapping to another line, the folded panel opened under it), tell it, so the
  // view does not leave gaps. The centre stays where it was: it is the keyboard's cell cursor. (To
  // the pixel: Leaflet pans by whole pixels, so a change by an odd number of them moves it by half.)
  if (window.ResizeObserver) {
    new ResizeObserver(() => map.invalidateSize({ pan: true, animate: false })).observe($('map'));
  }
}
