/*
 * The side panel's folded form (narrow screens): the button that opens and closes it, and its one
 * line of summary (the last cell queried, else the robots).
 */
import { $, sideSummary, sideToggle } from './dom.js';
import { robotState } from './robots.js';
import { state } from './state.js';

/** The folded panel's one line (narrow screens): the last cell queried, else the robots. */
export function renderSideSummary() {
  let text = state.cellSummary || '';
  if (!text && state.robots.size) {
    const online = [...state.robots.values()].filter((r) => robotState(r) === 'online').length;
    // Without a connected stream the list says 'unknown': '0 online' would say they all went.
    const known = state.connection === 'connected';
    text = `${state.robots.size} robot${state.robots.size === 1 ? '' : 's'}, `
      + (known ? `${online} online` : 'state unknown');
  }
  if (sideSummary.textContent !== text) sideSummary.textContent = text;
}

/** Open and close the folded panel with its button. */
export function toggleSidePanelOnClick() {
  sideToggle.addEventListener('click', () => {
    const open = sideToggle.getAttribute('aria-expanded') !== 'true';
    sideToggle.setAttribute('aria-expanded', String(open));
    $('side').dataset.open = String(open);
  });
}
