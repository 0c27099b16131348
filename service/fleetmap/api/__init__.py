"""fleetmap's REST API (FastAPI): `create_app(registry, settings=ApiSettings(...))`.

Modules: `app` (the app and its settings), `state` (what routes share), `errors` (every error is
`{"detail": ...}` JSON), `routes_service` (health, metrics),
`routes_maps` (maps, scans), `routes_data` (cells, rays,
regions, surfaces, exports), `routes_tiles` (PNG tiles), `routes_snapshot` (a map as one file,
down and up), `routes_import` (a map from a nav2 map), `events` (server-sent events) with
`robots_feed` (what a stream has sent of the robots), `routes_session` (a browser's sign-in),
`signin_limit` (failed sign-ins per client address), `conditional` (If-Match / If-None-Match on map
writes), `strict_requests` (how bodies and query parameters are read), `http_semantics` (HEAD,
caching headers, gzip, ETags), `priority` (requests wait while scans wait), `security_headers`
(nosniff, framing, referrer, the viewer's Content-Security-Policy), `static` (web viewer and
Leaflet). Request and response models are in `fleetmap.api_models`; docs/api.md describes it all.
"""

from fleetmap.api.app import ApiSettings, create_app

__all__ = ["ApiSettings", "create_app"]
