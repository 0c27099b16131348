/*
 * The robot list in the side panel: a row per robot (a button that centres the map on it) with its
 * colour, name, state and scan count. renderRobotList updates rows in place, keyed by robot id, and
 * adds or removes rows only when robots come or go (state.listChanged).
 */
import { robotCount, robotList } from './dom.js';
import { map } from './leaflet-map.js';
import { naturalOrder, robotState } from './robots.js';
import { renderSideSummary } from './side-panel.js';
import { state, stats } from './state.js';

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
export function renderRobotList(changed) {
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
  // Rows join or leave the list only when robots come or go, in their order. The rows that stay are
  // left where they are: rebuilt whole (replaceChildren), every row was taken out and put back, and
  // a row taken out loses the keyboard focus, so a user tabbing through the robots lost their place
  // whenever one came or went.
  const ids = [...state.robots.keys()].sort(naturalOrder.compare);
  const rows = ids.map((id) => state.robots.get(id).row).filter(Boolean);
  const kept = new Set(rows);
  for (const el of [...robotList.children]) {
    if (!kept.has(el)) el.remove(); // a robot gone, or the 'no robots' line
  }
  rows.forEach((row, k) => {
    if (robotList.children[k] !== row) robotList.insertBefore(row, robotList.children[k] ?? null);
  });
}

/** Write a robot's state and scan count into its row, where they changed; true if any did. */
function renderRow(robot) {
  const shown = robotState(robot);
  const li = robot.row;
  const online = shown === 'unknown' ? 'unknown' : String(shown === 'online');
  const n = robot.data.scans_integrated ?? 0;
  const scans = `${n} scan${n === 1 ? '' : 's'}`;
  const st = li.children[0].children[2]; // button > .online-state (see robotRow)
  const scansEl = li.children[0].children[3]; // button > .scans
  if (li.dataset.online === online && st.textContent === shown && scansEl.textContent === scans) return false;
  li.dataset.online = online;
  if (st.textContent !== shown) st.textContent = shown;
  if (scansEl.textContent !== scans) scansEl.textContent = scans;
  return true;
}
