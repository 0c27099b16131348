/*
 * The page's elements (index.html) that the viewer reads and writes, looked up once by id. A module
 * script runs after the page is parsed, so every one of them exists. `$` looks up any other by id.
 */
export const $ = (id) => document.getElementById(id);
export const mapSelect = $('map-select');
export const layerSelect = $('layer-select');
export const statusEl = $('status');
export const statusTextEl = $('status-text');
export const lastUpdateEl = $('last-update');
export const coordsEl = $('coords');
export const emptyEl = $('empty');
export const noScansEl = $('no-scans');
export const noScansKey = $('no-scans-key');
export const robotList = $('robot-list');
export const robotCount = $('robot-count');
export const cellInfo = $('cell-info');
export const cellForm = $('cell-form');
export const cellX = $('cell-x');
export const cellY = $('cell-y');
export const cellFormError = $('cell-form-error');
export const cellAnnounce = $('cell-announce');
export const sideToggle = $('side-toggle');
export const sideSummary = $('side-summary');
export const errorEl = $('error');
export const signInEl = $('sign-in');
export const signInForm = $('sign-in-form');
export const signInToken = $('sign-in-token');
export const signInError = $('sign-in-error');
export const signOutButton = $('sign-out');
