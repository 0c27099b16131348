"""How the routes read what FastAPI parses for them: JSON bodies and query parameters, strictly.

`StrictRoute` (every router's `route_class`) answers, before the route runs:

- 415 for a JSON body sent with another Content-Type (a `curl -d` sends form encoding), or none:
  FastAPI would pass the bytes on as they are and answer a puzzling "Input should be a valid
  dictionary";
- 413 for a JSON body of a route with a limit of values (`limit_json_values`: the points of
  `POST .../cells`, the rays of `.../raycast`, a map configuration of `PUT /maps/{id}`) that holds
  more commas than a valid body can, before it is parsed;
- 422 for a JSON body that holds a key twice (`{"resolution": 0.05, "resolution": 0.1}`): the JSON
  parser would keep the last one silently, and which one the client meant is a guess;
- 422 for a JSON body starting with a byte order mark, as `POST /scans` (whose codec is also that of
  Zenoh messages) refuses it: one rule for every body (RFC 8259 forbids sending one);
- 422 naming the reason for any other body that is not JSON (e.g. an integer of more digits than
  Python converts), where FastAPI said "could not be decoded";
- 422 for a query parameter of the route given twice (`?x=0&x=5`): FastAPI would take the last;
- 422 for a number (a query or path parameter of type int or float) written with an underscore:
  pydantic reads `1_0` as 10, so a typo (`x=1_0.5`) was answered for another place than asked;
- 422 for an integer parameter (a tile's z, x and y, a margin, ...) not written in plain decimal
  (`01`, `+1`, `1.0`, ` 1`, `-0`): pydantic reads each as the number, so one tile had many URLs,
  each cached apart by browsers and proxies.

Query parameters a route does not take are ignored, as caches and tile clients add their own
(`?v=2`, `?_=<time>`) to bust caches.
"""

from __future__ import annotations

import email.message
import json
import re
import types
import typing
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import Request, Response
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException as StarletteHTTPException

from fleetmap.api.errors import ApiError
from fleetmap.api_models import ErrorItem
from fleetmap.codec import UTF8_BOM, repeated_key


class RequestRefused(StarletteHTTPException):
    """A body or query FastAPI would misread. An HTTPException, so FastAPI's body parsing passes it on
    as is (it turns other exceptions raised while parsing into a 400)."""


def is_json_media_type(content_type: str) -> bool:
    """Whether `content_type` is JSON (`application/json`, or `application/<x>+json`), with any
    parameters (charset)."""
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    json_subtype = subtype == "json" or subtype.endswith("+json")
    return message.get_content_maintype() == "application" and json_subtype


def _not_json(reason: str) -> RequestRefused:
    return RequestRefused(422, f"body is not valid JSON for this API: {reason}")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    repeated = repeated_key(pairs)
    if repeated is not None:
        raise _not_json(f"the key {repeated!r} appears twice in an object")
    return dict(pairs)


def parse_json_body(body: bytes) -> Any:
    """The JSON value of a request body; RequestRefused (422) saying why if it is not one."""
    if body.startswith(UTF8_BOM):
        raise _not_json("it starts with a byte order mark; send UTF-8 without one")
    try:
        return json.loads(body.decode("utf-8"), object_pairs_hook=_unique_keys)
    except UnicodeDecodeError as exc:
        raise _not_json(f"it is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise _not_json(f"{exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except ValueError:  # not a syntax error: an integer of more digits than int() converts
        raise _not_json("a number in it has too many digits") from None
    except RecursionError:
        raise _not_json("it is nested too deeply") from None


#: Per route (its path template): the most commas a valid JSON body of it can hold, and what it
#: counts (`limit_json_values`). A body past that is refused (413) before it is parsed: parsing is
#: what costs. A `POST .../cells` body of 16 MiB (the body limit) holds 2.8 million points, which
#: `json.loads` took 1.3 s and 300 MB to build, holding the GIL, so the event loop served nothing
#: else meanwhile, before the model refused them as more than 100,000.
_JSON_VALUE_LIMITS: dict[str, tuple[int, str]] = {}


def limit_json_values(path: str, commas: int, what: str) -> None:
    """Refuse a JSON body of route `path` holding more than `commas` commas (counted in its bytes,
    strings included: a bound on the values it holds) with 413, saying it holds more than `what`."""
    _JSON_VALUE_LIMITS[path] = (commas, what)


class StrictRequest(Request):
    """A request whose `json()` is `parse_json_body`'s (what FastAPI calls for JSON bodies)."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            self._json = parse_json_body(await self.body())
        return self._json


def _query_names(dependant: Dependant) -> set[str]:
    """The query parameters a route takes, its dependencies' included."""
    names = {param.alias for param in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_names(sub)
    return names


def _number_params(dependant: Dependant) -> list[tuple[str, str, bool]]:
    """The route's query and path parameters that are numbers (int or float, or optionally one), as
    (where, name, whether it is an integer) triples, its dependencies' included."""
    found = [
        (where, param.alias, _is_integer(param.field_info.annotation))
        for where, params in (("query", dependant.query_params), ("path", dependant.path_params))
        for param in params
        if _is_number(param.field_info.annotation)
    ]
    for sub in dependant.dependencies:
        found += _number_params(sub)
    return found


def _is_number(annotation: Any) -> bool:
    """Whether a parameter of type `annotation` is a number: int, float, or a union holding one."""
    return any(member in (int, float) for member in _members(annotation))


def _is_integer(annotation: Any) -> bool:
    """Whether a parameter of type `annotation` is an integer: int, or a union holding int and no float."""
    members = _members(annotation)
    return int in members and float not in members


def _members(annotation: Any) -> tuple[Any, ...]:
    """The types a parameter of type `annotation` may hold: a union's members, or itself."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return typing.get_args(annotation)
    return (annotation,)


#: An integer as a client writes it when it means one number by one URL: plain decimal digits, a
#: minus sign for a negative one, no leading zero.
_PLAIN_INTEGER = re.compile(r"0|-?[1-9][0-9]*")


def _not_a_plain_number(value: str, integer: bool) -> str | None:
    """Why a number parameter's `value` is refused, or None: an underscore anywhere; for an integer,
    any other form than plain decimal."""
    if "_" in value:
        return "not a number (no underscores)"
    if integer and not _PLAIN_INTEGER.fullmatch(value):
        return "not an integer in plain decimal (digits, '-' if negative, no leading zero)"
    return None


class StrictRoute(APIRoute):
    """An APIRoute reading its JSON body and query parameters strictly (see the module's docstring)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        takes_body = self.body_field is not None
        query_names = _query_names(self.dependant)
        number_params = _number_params(self.dependant)

        async def strict_handler(request: Request) -> Response:
            for where, name, integer in number_params:
                value = (request.query_params if where == "query" else request.path_params).get(name)
                why = _not_a_plain_number(value, integer) if isinstance(value, str) else None
                if why is not None:
                    raise ApiError(
                        422,
                        f"{where} parameter {name!r}: {value!r} is {why}",
                        errors=[ErrorItem(loc=[where, name], msg=why, type="number")],
                    )
            repeated = sorted({key for key in query_names if len(request.query_params.getlist(key)) > 1})
            if repeated:
                # One problem per parameter in `errors`, as a validation failure lists them.
                problems = [
                    ErrorItem(loc=["query", key], msg="given more than once; give it once", type="repeated")
                    for key in repeated
                ]
                more = f" (and {len(repeated) - 1} more)" if len(repeated) > 1 else ""
                raise ApiError(
                    422,
                    f"query parameter {repeated[0]!r} is given more than once; give it once{more}",
                    errors=problems,
                )
            request = StrictRequest(request.scope, request.receive)
            values = _JSON_VALUE_LIMITS.get(self.path) if takes_body else None
            if values is not None and (await request.body()).count(b",") > values[0]:
                raise RequestRefused(
                    413, f"the body holds more than {values[1]} (the limit per request); it was not read"
                )
            content_type = request.headers.get("content-type")
            # An empty body is no body, whatever its type (PUT /maps/{id} then takes the defaults).
            wrong_type = takes_body and not (content_type and is_json_media_type(content_type))
            if wrong_type and await request.body():
                sent = f"not {content_type!r}" if content_type else "none was given"
                raise RequestRefused(
                    415, f"the body must be JSON, with Content-Type: application/json ({sent})"
                )
            return await handler(request)

        return strict_handler
