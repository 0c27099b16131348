/*
 * What the page says about itself: the status line (the event stream's connection state and the time
 * of the last update: setConnection, renderStatus) and the error messages of the side panel
 * (showError, which fades; clearNetworkError and clearError take back what is no longer true).
 * reportUncaughtErrors shows any uncaught error or rejection there too, rather than only in the
 * console.
 */
import { ERROR_SHOW_MS } from './config.js';
import { errorEl, lastUpdateEl, signInEl, statusEl, statusTextEl } from './dom.js';
import { redrawRobots } from './robots.js';
import { state } from './state.js';

/**
 * Show an error in the side panel (never thrown at the user); it fades after a while.
 * `network`: the message is about the service being unreachable; a reconnect clears it.
 */
export function showError(message, network = false) {
  // While the page asks for a token, what failed for want of one is no news (the form says it).
  if (!signInEl.hidden) return;
  errorEl.textContent = `${new Date().toLocaleTimeString()}: ${message}`;
  errorEl.hidden = false;
  errorEl.dataset.network = String(network);
  clearTimeout(state.errorTimer);
  state.errorTimer = setTimeout(() => { errorEl.hidden = true; }, ERROR_SHOW_MS);
}

/** The service answers again: a message saying it cannot be reached is no longer true. */
export function clearNetworkError() {
  if (!errorEl.hidden && errorEl.dataset.network === 'true') {
    clearTimeout(state.errorTimer);
    errorEl.hidden = true;
  }
}

/** An error the page said that is no longer true (e.g. the map a link named has appeared): hide it. */
export function clearError(message) {
  if (!errorEl.hidden && errorEl.textContent.endsWith(`: ${message}`)) {
    clearTimeout(state.errorTimer);
    errorEl.hidden = true;
  }
}

/** Show every uncaught error and unhandled rejection of the page as an error message. */
export function reportUncaughtErrors() {
  window.addEventListener('error', (e) => showError(e.message || String(e)));
  window.addEventListener('unhandledrejection', (e) => showError(String(e.reason && e.reason.message || e.reason)));
}

/** The status line: connection state of the event stream and the time of the last update. */
export function setConnection(conn) {
  const was = state.connection;
  state.connection = conn;
  renderStatus();
  // Robots are online or offline only as far as a connected stream tells; else 'unknown'.
  if ((was === 'connected') !== (conn === 'connected')) redrawRobots();
}

/** Write the status line from state.connection and state.lastUpdate, touching only what changed. */
export function renderStatus() {
  const texts = {
    starting: 'starting…',
    waiting: 'waiting for robots…',
    connecting: 'connecting to events…',
    connected: 'connected',
    reconnecting: 'reconnecting to events…',
    error: 'event stream lost; retrying…',
    unreachable: 'cannot reach the service; retrying…',
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
