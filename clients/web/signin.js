/*
 * Signing in and out (the app.js header, "Signing in"): needSignIn shows the form over the map when a
 * read is refused (401), and clears the page of the maps; the form posts its token once to `session`,
 * which answers with an HttpOnly session cookie; "Sign out" deletes it. Whether this browser holds a
 * session is kept in localStorage (SIGNED_IN_KEY), for the "Sign out" button.
 */
import { SIGNED_IN_KEY, TOKEN_CHARS } from './config.js';
import {
  emptyEl, errorEl, mapSelect, signInEl, signInError, signInForm, signInToken, signOutButton,
} from './dom.js';
import { deselectMap, refreshMaps, setMapOptions } from './maps.js';
import { errorDetail } from './rest.js';
import { state } from './state.js';
import { setConnection, showError } from './status.js';

/** What the form says when it takes the place of a session's map (see needSignIn). */
const SESSION_ENDED = 'Your session has ended: its token was revoked or replaced, or this browser signed '
  + 'out in another tab or was closed since. Sign in again to see the maps.';

/**
 * A read was refused for want of a valid token: nothing of the maps stays on the page (its user
 * may no longer see them; the URL keeps the map and view, shown again after signing in), and the
 * sign-in form takes the map's place. Where this browser held a session (it showed "Sign out"), the
 * form says the session ended: a map being watched vanished with no word of why.
 */
export function needSignIn() {
  if (!signInEl.hidden) return;
  const ended = !signOutButton.hidden; // signing out hides it first: no news to the user who asked
  deselectMap(true);
  setMapOptions([]);
  mapSelect.disabled = true;
  emptyEl.hidden = true;
  clearTimeout(state.errorTimer);
  errorEl.hidden = true;
  rememberSignedIn(false);
  signInError.textContent = ended ? SESSION_ENDED : '';
  signInError.hidden = !ended;
  signInToken.removeAttribute('aria-invalid');
  signInEl.hidden = false;
  setConnection('signin');
  signInToken.focus();
}

/**
 * Say why signing in failed, under the form's button (an alert: a screen reader says it).
 * `tokenWrong`: the token itself was refused (the field is marked invalid, to be corrected).
 */
function signInFailed(message, tokenWrong = true) {
  signInError.textContent = message;
  signInError.hidden = false;
  if (tokenWrong) signInToken.setAttribute('aria-invalid', 'true');
  else signInToken.removeAttribute('aria-invalid');
  signInToken.focus();
}

/** Whether this browser holds a session: shows "Sign out" (kept over reloads, see SIGNED_IN_KEY). */
function rememberSignedIn(signedIn) {
  signOutButton.hidden = !signedIn;
  try {
    if (signedIn) localStorage.setItem(SIGNED_IN_KEY, '1');
    else localStorage.removeItem(SIGNED_IN_KEY);
  } catch (_) { /* storage blocked: "Sign out" shows until the page is reloaded */ }
}

/**
 * The form goes (forgetting what was typed) and the maps are read: signed in, here or in another tab
 * (`session`), or without a session where none is needed (reads are open).
 */
function closeSignIn(session) {
  signInToken.value = '';
  signInToken.removeAttribute('aria-invalid');
  signInError.hidden = true;
  signInEl.hidden = true;
  rememberSignedIn(session);
  setConnection('starting');
  refreshMaps();
}

/** The status of a read made as this browser is (with the session cookie it keeps, if any); 0 if the
 * service cannot be reached. */
async function readStatus() {
  try {
    const resp = await fetch('maps', { headers: { Accept: 'application/json' }, cache: 'no-store' });
    return resp.status;
  } catch (_) {
    return 0;
  }
}

/** Handle the sign-in form and the "Sign out" button. */
export function handleSignInAndOut() {
  // The token goes to the service once, in a header; the page forgets it as soon as it is sent.
  signInForm.addEventListener('submit', async (e) => {
    e.preventDefault();
    const token = signInToken.value.trim();
    if (!TOKEN_CHARS.test(token)) {
      signInFailed(token ? 'a token holds printable ASCII characters only, no spaces' : 'enter your API token');
      return;
    }
    let resp;
    try {
      resp = await fetch('session', {
        method: 'POST',
        headers: { Authorization: `Bearer ${token}`, Accept: 'application/json' },
        cache: 'no-store',
      });
    } catch (err) {
      signInFailed(`cannot reach the service (${err.message})`, false);
      return;
    }
    // Refused, but reads may be open by now: the service restarted while the form was shown, without
    // tokens (then it answers 404: nothing to sign in to) or with tokens for writes only (a token no
    // longer listed: 401). The form stayed, saying so, and only a reload showed the maps, which need
    // no token: a read that works shows them. (A 404 is not taken for that alone: a proxy that does
    // not pass `session` on must not hide the form the reads still need.)
    if (!resp.ok && await readStatus() === 200) {
      closeSignIn(false);
      return;
    }
    // Only a 401 says the token is wrong; others (429: too many failed sign-ins from this address,
    // 503, ...) say nothing of it, and a right token must not be marked invalid.
    if (resp.status === 401) {
      signInFailed('unknown token: check it and try again');
      return;
    }
    if (!resp.ok) {
      signInFailed(`cannot sign in: ${resp.status} ${await errorDetail(resp)}`, false);
      return;
    }
    // The answer set the session cookie, but the browser may not keep it: cookies blocked for this
    // site, or a `Secure` one (a proxy told the service the request came over https) on a page served
    // over http. Then the form went, the first read was refused, and it came back at once, saying
    // nothing. A read tells; the page keeps no token either way.
    if (await readStatus() === 401) {
      signInToken.value = '';
      signInFailed('the service accepted the token, but this browser did not keep the session cookie: '
        + 'allow cookies for this site (behind a proxy: open the viewer over https if the proxy says '
        + 'https to the service)', false);
      return;
    }
    closeSignIn(true);
  });

  // Signing out clears the cookie; the next request then shows the form (or, if reads are open after
  // all, the page goes on as it is). Until the service has cleared it the browser is still signed
  // in: "Sign out" stays, to try again (it went at the click, and a sign-out that failed left a
  // session no button could end).
  signOutButton.addEventListener('click', async () => {
    let resp;
    try {
      resp = await fetch('session', { method: 'DELETE', cache: 'no-store' });
    } catch (err) {
      showError(`cannot sign out: cannot reach the service (${err.message})`, true);
      return;
    }
    if (!resp.ok) {
      showError(`cannot sign out: ${resp.status} ${await errorDetail(resp)}`);
      return;
    }
    rememberSignedIn(false);
    refreshMaps();
  });

  // Signed in in another tab of this browser (the cookie is shared): this tab's form, which no
  // request is made under, would have asked for the token again until reloaded. Signed out in
  // another: this tab's map, and its event stream opened with the cookie, went on until the next
  // poll of the maps (5 s; never in a tab whose polls stopped): a read now shows the form, saying
  // the session ended, or where reads are open the maps as anyone sees them, with no "Sign out".
  window.addEventListener('storage', async (e) => {
    if (e.key !== SIGNED_IN_KEY) return;
    if (e.newValue === '1' && !signInEl.hidden) closeSignIn(true);
    else if (e.newValue === null && signInEl.hidden && !signOutButton.hidden) {
      await refreshMaps();
      if (signInEl.hidden) signOutButton.hidden = true;
    }
  });

  // Clicks, drags and the wheel over the form are the form's, not the map's under it.
  L.DomEvent.disableClickPropagation(signInEl);
  L.DomEvent.disableScrollPropagation(signInEl);
}

/** Show "Sign out" if this browser signed in before (on an earlier page load). */
export function showSignOutIfSignedIn() {
  try {
    signOutButton.hidden = localStorage.getItem(SIGNED_IN_KEY) !== '1';
  } catch (_) { /* storage blocked: no "Sign out" until the user signs in on this page */ }
}
