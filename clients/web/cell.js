/*
 * The cell inspector: a click on the map, Enter with the map focused (the cell under the cross at the
 * centre) or a typed point asks GET maps/{id}/cell for one cell, outlines it on the map and shows its
 * values in the side panel, in a table and in one sentence for screen readers. clearCell forgets it.
 * An answer for a cell no longer asked about (state.cellToken) is dropped. The cell shown is asked
 * again, quietly, when the map's changes touch it (refreshCell): robots go on mapping it, and its
 * values stayed those of the click.
 */
import { MAX_METRES } from './config.js';
import { cellAnnounce, cellForm, cellFormError, cellInfo, cellX, cellY, coordsEl } from './dom.js';
import { map, toLatLng } from './leaflet-map.js';
import { enc, getJSON } from './rest.js';
import { renderSideSummary } from './side-panel.js';
import { state } from './state.js';
import { showError } from './status.js';

// Cell fields shown on click, in this order.
const CELL_FIELDS = ['known', 'probability', 'state', 'log_odds', 'hits', 'misses', 'tsdf', 'tsdf_weight'];
// The field of each layer that has a value in every cell of a map keeping the layer (an unknown
// cell's state is 'unknown', its counts and TSDF weight 0): the service answers null for the fields
// of a layer the map does not keep, and null is also an unknown cell's log odds or TSDF value.
const LAYER_OF_FIELD = {
  probability: 'state', state: 'state', log_odds: 'state', hits: 'hits', misses: 'hits',
  tsdf: 'tsdf_weight', tsdf_weight: 'tsdf_weight',
};

/** Whether the map keeps the layer of a cell's field (`known` is every map's). */
function kept(cell, key) {
  const probe = LAYER_OF_FIELD[key];
  return probe === undefined ? key in cell : cell[probe] !== null && cell[probe] !== undefined;
}

/** A cell value as the inspector shows it: a dash for none, yes / no, counts whole, others rounded. */
function fmt(v, key) {
  if (v === null || v === undefined || (typeof v === 'number' && Number.isNaN(v))) return '—';
  if (typeof v === 'boolean') return v ? 'yes' : 'no';
  if (typeof v === 'number') {
    if (key === 'hits' || key === 'misses' || Number.isInteger(v)) return String(v);
    return v.toFixed(key === 'probability' ? 4 : 3);
  }
  return String(v);
}

/** Forget the clicked cell (panel, outline, what was announced) and the cursor position. */
export function clearCell() {
  state.cellToken += 1; // an answer still on its way is for a cell no longer shown
  cellInfo.innerHTML = '<p class="none">Click the map, or type a point, to query a cell.</p>';
  delete cellInfo.dataset.i;
  delete cellInfo.dataset.j;
  state.cellShown = null;
  if (state.cellMarker) { state.cellMarker.remove(); state.cellMarker = null; }
  coordsEl.textContent = '';
  cellAnnounce.textContent = '';
  state.cellSummary = '';
  renderSideSummary();
}

/** Query cells from clicks, the keyboard (Enter) and the typed point form. */
export function queryCellsOnInput() {
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
}

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

/** The outline of cell (i, j), and a ring of fixed screen size so it can be found at any zoom. */
function drawCellMarker(i, j) {
  if (state.cellMarker) state.cellMarker.remove();
  state.cellMarker = L.featureGroup([
    L.rectangle([[j, i], [j + 1, i + 1]], { color: '#0969da', weight: 2, fill: false, interactive: false }),
    L.circleMarker([j + 0.5, i + 0.5], { radius: 9, color: '#0969da', weight: 2, fill: false, interactive: false }),
  ]).addTo(map);
}

/**
 * Ask for cell (i, j) and show its values. `point`: the [x, y] in metres to ask at (a typed point);
 * by default the cell's centre (no rounding doubts at cell edges). `again`: the cell shown, asked
 * again because it changed (refreshCell): its values are replaced in place, not announced (a live
 * region that spoke with every scan would drown the rest), and a failure keeps the last ones.
 */
async function queryCell(i, j, point = null, again = false) {
  if (!state.mapId) return;
  const token = ++state.cellToken;
  const [x, y] = point || [(i + 0.5) * state.res, (j + 0.5) * state.res];
  if (!again) {
    drawCellMarker(i, j);
    cellInfo.innerHTML = '<p class="none">querying…</p>';
  }
  try {
    const cell = await getJSON(`maps/${enc(state.mapId)}/cell?x=${x}&y=${y}`);
    if (token !== state.cellToken) return;
    // The service says which cell it answered for (i, j); trust it over our own arithmetic.
    const ci = Number.isInteger(cell.i) ? cell.i : i;
    const cj = Number.isInteger(cell.j) ? cell.j : j;
    if (ci !== i || cj !== j) drawCellMarker(ci, cj);
    state.cellShown = { i: ci, j: cj, point };
    renderCell(ci, cj, x, y, cell, !again);
    if (!point && !again) {
      cellX.value = String(+x.toFixed(3));
      cellY.value = String(+y.toFixed(3));
    }
  } catch (err) {
    if (token !== state.cellToken || again) return;
    cellInfo.innerHTML = '<p class="none">no value</p>';
    announceCell(`cell query failed: ${err.message}`);
    showError(`cell query: ${err.message}`, !!err.network);
  }
}

/**
 * The map changed in `windows` (cell windows [i0, j0, i1, j1), as the `tiles` event gives them), or
 * everywhere (`reset`): ask again for the cell shown when they hold it. Called once per redraw of
 * the tiles (tiles.js), so at most as often as tiles are.
 */
export function refreshCell(windows, reset) {
  const shown = state.cellShown;
  if (!shown || !state.mapId) return;
  const { i, j } = shown;
  if (reset || windows.some((w) => w[0] <= i && i < w[2] && w[1] <= j && j < w[3])) {
    queryCell(i, j, shown.point, true);
  }
}

/** One sentence for the live region (`spoken`) and the folded panel's line. */
function announceCell(text, spoken = true) {
  if (spoken) cellAnnounce.textContent = text;
  state.cellSummary = text;
  renderSideSummary();
}

/** What a cell holds, in words: its state and probability, its counts, its TSDF value. */
function cellSentence(i, j, x, y, cell) {
  const parts = [];
  if (kept(cell, 'state')) parts.push(String(cell.state));
  if (kept(cell, 'probability') && cell.known) parts.push(`probability ${fmt(cell.probability, 'probability')}`);
  if (kept(cell, 'hits')) parts.push(`${fmt(cell.hits, 'hits')} hits, ${fmt(cell.misses, 'misses')} misses`);
  if (!kept(cell, 'state') && kept(cell, 'tsdf')) parts.push(`TSDF ${fmt(cell.tsdf, 'tsdf')}`);
  return `Cell (${i}, ${j}) at x ${x.toFixed(2)} m, y ${y.toFixed(2)} m: ${parts.join(', ')}`;
}

/** Show the values of cell (i, j), asked at (x, y); `spoken`: say them in the live region too. */
function renderCell(i, j, x, y, cell, spoken) {
  const where = document.createElement('p');
  where.className = 'where';
  where.textContent = `cell (${i}, ${j}) · x ${x.toFixed(3)} m, y ${y.toFixed(3)} m`;
  const table = document.createElement('table');
  for (const key of CELL_FIELDS) {
    if (!kept(cell, key)) continue; // a layer the map does not keep
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
  announceCell(cellSentence(i, j, x, y, cell), spoken);
}
