/*
 * The robots layer: each robot's marker and trail on the map, from `robots` events (every robot),
 * `robots_delta` events (the robots that changed and their new trail points) and GET maps/{id}'s
 * stats.robots (maps.js).
 * A robot's marker and trail are made once, then moved and turned in place, and only when its report
 * changed; drawing waits for the next animation frame, once however many events came before it.
 * state.robots holds each robot ({id, color, data, marker, trail, row, drawn, trailEdit}); the list
 * in the side panel is robot-list.js's.
 */
import { map, toLatLng } from './leaflet-map.js';
import { renderRobotList } from './robot-list.js';
import { state, stats } from './state.js';

// Robot (and map) ids in natural order: sim-2 before sim-10.
export const naturalOrder = new Intl.Collator(undefined, { numeric: true, sensitivity: 'base' });
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

// Trails stay SVG paths: one canvas for all of them (L.canvas) was measured dearer, since the whole
// canvas bitmap (twice the view with Leaflet's padding) is handed to the compositor on every redraw
// (docs/benchmarks.md, "Web viewer").
const robotLayer = L.layerGroup();

/** Put the robots' layer on the map. */
export function addRobotLayer() {
  robotLayer.addTo(map);
}

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
export function updateRobots(reports, complete = false, edits = null) {
  reports = reports || {};
  if (complete) {
    for (const id of [...state.robots.keys()]) {
      if (!Object.hasOwn(reports, id)) removeRobot(id); // not `in`: 'constructor' is in every object
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
export function applyRobotsDelta(delta) {
  for (const id of delta.removed || []) removeRobot(id);
  // No prototype: a robot may be called __proto__ (the id pattern allows it), and assigning that
  // key of a plain object sets its prototype instead, so the robot's changes were never drawn.
  const reports = Object.create(null);
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
export function robotState(robot) {
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
export function redrawRobots() {
  for (const robot of state.robots.values()) drawRobot(robot, true);
  renderRobotList(state.robots.values());
}

/** Forget every robot: off the map and out of the list; colours start from the first again. */
export function clearRobots() {
  robotLayer.clearLayers();
  state.robots.clear();
  state.dirtyRobots.clear();
  state.robotsSeen = 0;
  state.listChanged = true;
  renderRobotList([]);
}
