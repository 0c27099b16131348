"""fleetmap's REST API (FastAPI): `create_app(registry, settings=ApiSettings(...))`.

Modules: `app` (the app and its settings), `state` (what routes share), `errors` (every error is
`{"detail": ...}` JSON), `routes_maps` (health, metrics, maps, scans), `routes_data` (cells, rays,
regions, surfaces, exports), `routes_tiles` (PNG tiles), `events` (server-sent events),
`routes_session` (a browser's sign-in), `signin_limit` (failed sign-ins per client address),
`security_headers` (nosniff, framing, referrer, the viewer's Content-Security-Policy), `static` (web
viewer and Leaflet). Request and response models
are in `fleetmap.api_models`; docs/api.md describes it all.
"""

from fleetmap.api.app import ApiSettings, create_app

__all__ = ["ApiSettings", "create_app"]
