/*
 * The URL hash: #map=<id>&layer=<layer>, and once the user moves the map the view too:
 * &x=<metres>&y=<metres>&z=<zoom> (the centre), so a link shows the same place. readHash parses it,
 * writeHash rewrites it from the state (replacing, never pushing, a history entry). trackChosenView
 * notes the user's own moves; followHashEdits applies a hash someone edited (or a link followed).
 */
import { MAX_METRES, MAX_ZOOM, MIN_ZOOM } from './config.js';
import { layerSelect, mapSelect } from './dom.js';
import { map, showView } from './leaflet-map.js';
import { refreshMaps, selectMap } from './maps.js';
import { state } from './state.js';
import { showError } from './status.js';

/** The hash's map, layer and view ({x, y, z}: centre in metres and zoom; null unless all three are
 * numbers, the centre within MAX_METRES, the zoom within the viewer's range). */
export function readHash() {
  const p = new URLSearchParams(location.hash.replace(/^#/, ''));
  const num = (k) => (p.get(k) === null || p.get(k).trim() === '' ? NaN : Number(p.get(k)));
  const [x, y, z] = [num('x'), num('y'), num('z')];
  const view = Math.abs(x) <= MAX_METRES && Math.abs(y) <= MAX_METRES
    && Number.isInteger(z) && z >= MIN_ZOOM && z <= MAX_ZOOM ? { x, y, z } : null;
  return { map: p.get('map'), layer: p.get('layer'), view };
}

/**
 * The view shown, as the hash writes it: centre in metres and zoom. The centre is rounded to the
 * centimetre, or finer where a centimetre is more than a screen pixel at the zoom shown (a map of
 * millimetre cells zoomed in: 0.01 m was 80 pixels at 2 mm and zoom 4, so a link opened up to 40
 * pixels away, and the cross at the centre on another cell).
 */
function currentView() {
  const c = map.getCenter();
  const z = map.getZoom();
  const metresPerPixel = state.res / 2 ** z;
  // Rounding moves the centre by at most half a unit of the last digit: half a pixel at most.
  const digits = Math.min(10, Math.max(2, Math.ceil(-Math.log10(metresPerPixel))));
  return { x: +(c.lng * state.res).toFixed(digits), y: +(c.lat * state.res).toFixed(digits), z };
}

/** Replace (not push) the hash: switching maps or panning should not fill the back button's history. */
export function writeHash() {
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

/** Count a move the page did not make itself as the user's choice of view, kept in the URL. */
export function trackChosenView() {
  // A move the page did not make itself (a drag, the wheel, the keys, a robot row, a typed point) is
  // the user's choice of view; from then on the URL carries the view shown, for a link to it.
  map.on('movestart', () => { if (!state.quietMove && state.mapId) state.viewChosen = true; });
  map.on('moveend', () => { if (state.viewChosen && state.mapId) writeHash(); });
}

/** Apply the hash when someone edits it. */
export function followHashEdits() {
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
    // The URL names what is shown, whatever the edit left out or named out of range (no layer, a
    // view beyond the limits): a link copied from it showed another layer, or the map fitted.
    writeHash();
  });
}
