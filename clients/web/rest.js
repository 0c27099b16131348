/*
 * Talking to the service's REST API: getJSON (a JSON read; a 401 shows the sign-in form), the reason
 * of an error answer (errorDetail), and `enc` for the ids in a URL. URLs are relative to the page, so
 * a path prefix (a reverse proxy) works.
 */
import { needSignIn } from './signin.js';

export const enc = encodeURIComponent;

/**
 * Fetch JSON; throws an Error whose message is the service's error message when there is one. A 401
 * (the service needs a token to read, or the session's token was revoked) shows the sign-in form.
 */
export async function getJSON(url) {
  let resp;
  try {
    resp = await fetch(url, { headers: { Accept: 'application/json' }, cache: 'no-store' });
  } catch (err) {
    const e = new Error(`cannot reach the service (${err.message})`);
    e.network = true;
    throw e;
  }
  if (!resp.ok) {
    if (resp.status === 401) needSignIn();
    const err = new Error(`${url}: ${resp.status} ${await errorDetail(resp)}`);
    err.status = resp.status;
    throw err;
  }
  return resp.json();
}

/** The service's reason for an error answer (its JSON `detail`), else the status text. */
export async function errorDetail(resp) {
  try {
    const body = await resp.json();
    return typeof body.detail === 'string' ? body.detail : JSON.stringify(body.detail ?? body);
  } catch (_) {
    return resp.statusText; // not JSON
  }
}
