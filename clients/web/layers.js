/*
 * The layer selector: the tile layers the service renders, the ones the selected map keeps
 * (setLayerOptions, from its config.layers), and switching between them (state.layer, the hash and
 * every tile's URL).
 */
import { layerSelect } from './dom.js';
import { readHash, writeHash } from './hash.js';
import { map } from './leaflet-map.js';
import { state } from './state.js';
import { showError } from './status.js';
import { tiles } from './tiles.js';

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

/** Fill the layer selector with the tile layers this map keeps; keep the wanted one if possible. */
export function setLayerOptions(mapLayers) {
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

/** Show the layer the user picks. */
export function switchLayerOnChange() {
  layerSelect.addEventListener('change', () => {
    state.layer = layerSelect.value;
    writeHash();
    state.tileCounter += 1;
    if (map.hasLayer(tiles)) tiles.redraw();
  });
}
