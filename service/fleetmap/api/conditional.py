"""Conditional writes on a map (RFC 9110, 13): `If-Match` and `If-None-Match` on `PUT /maps/{id}`,
`DELETE /maps/{id}`, `PUT /maps/{id}/snapshot`, `PUT /maps/{id}/import`, `DELETE
/maps/{id}/region` and `POST /maps/{id}/scans`, so that two operators
(or scripts) acting on one map cannot clobber each other: each sends the `ETag` it read, and the
second write finds the map changed (412) instead of undoing the first.

The map's entity tag (`map_etag`) is strong and names one incarnation of the map: it changes when
the map is created, replaced (snapshot or nav2 upload), or deleted and created again, and when the
service restarts (a restarted service may hold another map under the id). A map's configuration is
fixed for its life (`PUT` with another one is a 409), so the tag validates the configuration too. It
does not change with scans: the cells and statistics change many times a second while robots map,
and a tag that followed them would make every conditional write on a live map fail. So `GET
/maps/{id}` answers it as its `ETag` with `Cache-Control: no-store` (the statistics in the body
move while the tag stays: no cache may keep the body and revalidate it with the tag; a client that
sends the tag as `If-None-Match` itself gets 304, "same map, same configuration"), and it is the
same whether the answer is gzipped or not (it validates the map, not the bytes: `DefaultHeaders`
leaves it strong, so a client can send it back whatever encoding it accepted).

The conditions are evaluated where the write takes effect, under the registry's lock
(`MapRegistry.create`, `replace`, `delete` and `submit` call `Preconditions.check` there; `clear_window`
under the map's lock, where a map's removal also takes effect), so two writers
sending the same tag cannot both pass: exactly one wins, the other gets 412 with nothing changed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Header, Request, Response

from fleetmap.api.errors import ApiError
from fleetmap.api.http_semantics import generation_etag, joined_field_lines, strong_match, weak_match
from fleetmap.map_entry import Expectation, MapEntry

#: One entity tag of a list (RFC 9110, 8.8.3): optionally `W/`, then a quoted opaque tag (any
#: visible character but `"`, and obs-text).
_ENTITY_TAG = re.compile(r'(W/)?"([\x21\x23-\x7e\x80-\xff]*)"')


def map_etag(entry: MapEntry) -> str:
    """The strong entity tag of map `entry` (see the module's docstring), from its generation."""
    return generation_etag(entry.generation)


def tag_map(response: Response, entry: MapEntry) -> None:
    """Put map `entry`'s `ETag` on an answer that shows it (GET, and the writes that made or found
    it), `no-store`: its statistics change while the tag stays, so no cache may keep the body to
    revalidate with the tag (a 304 would show stale statistics)."""
    response.headers["ETag"] = map_etag(entry)
    response.headers["Cache-Control"] = "no-store"


def parse_entity_tags(value: str, header: str) -> list[str] | None:
    """The entity tags of an `If-Match` / `If-None-Match` value as sent (`W/` kept), or None for
    `*`. Several field lines are joined with commas by the caller. ApiError 422, naming `header`, for
    a value that is neither `*` nor a comma-separated list of quoted tags (`abc` unquoted, a `*` in
    a list): guessing what was meant could let a write through that the client meant to guard."""
    text = value.strip(" \t")
    if text == "*":
        return None
    tags: list[str] = []
    pos = 0
    while True:
        while pos < len(text) and text[pos] in " \t,":  # empty list elements are allowed (RFC 9110, 5.6.1)
            pos += 1
        if pos == len(text):
            break
        match = _ENTITY_TAG.match(text, pos)
        if match is None:
            raise ApiError(
                422,
                f"header {header}: {value!r} is not '*' nor a list of entity tags in double quotes "
                '(as an ETag is sent: "map-1234")',
            )
        tags.append(match.group(0))
        pos = match.end()
        while pos < len(text) and text[pos] in " \t":
            pos += 1
        if pos < len(text) and text[pos] != ",":
            raise ApiError(422, f"header {header}: {value!r} is not a comma-separated list of entity tags")
    if not tags:
        raise ApiError(422, f"header {header} is empty: send '*' or the ETag to compare")
    return tags


@dataclass(frozen=True)
class Preconditions:
    """The `If-Match` and `If-None-Match` of a write: the tags listed (None: none listed), and whether
    the header was `*` (`match_any`, `none_match_any`)."""

    if_match: list[str] | None = None
    match_any: bool = False
    if_none_match: list[str] | None = None
    none_match_any: bool = False

    @property
    def given(self) -> bool:
        """Whether the request carried either header."""
        listed = self.if_match is not None or self.if_none_match is not None
        return listed or self.match_any or self.none_match_any

    def expectation(self, map_id: str) -> Expectation | None:
        """The check the registry runs under its lock where the write takes effect (`check` for map
        `map_id`), or None when the request carried no condition."""
        if not self.given:
            return None
        return lambda entry: self.check(map_id, entry)

    def check(self, map_id: str, entry: MapEntry | None) -> None:
        """Raise ApiError 412 unless the conditions hold for the map as it is now (`entry`, None when
        there is none), in RFC 9110 13.2.2's order: `If-Match` first (strong comparison; `*`: the map
        exists; a list: its tag is one of them, so never when there is no map), then `If-None-Match`
        (weak comparison; `*`: there is no map). The 412 carries the map's current `ETag`, if any, so
        a client can read what changed and decide again."""
        current = None if entry is None else map_etag(entry)
        headers = {} if current is None else {"ETag": current}
        if self.match_any and current is None:
            raise ApiError(412, f"If-Match: * but there is no map {map_id!r}", headers=headers)
        if self.if_match is not None:
            if current is None:
                raise ApiError(412, f"If-Match: there is no map {map_id!r}", headers=headers)
            if not any(strong_match(tag, current) for tag in self.if_match):
                weak = (
                    ' (a weak tag W/"..." never matches If-Match)'
                    if any(t.startswith("W/") for t in self.if_match)
                    else ""
                )
                raise ApiError(
                    412,
                    f"If-Match: map {map_id!r} changed: its ETag is now {current}, not "
                    f"{', '.join(self.if_match)}{weak}",
                    headers=headers,
                )
        if self.none_match_any and current is not None:
            raise ApiError(412, f"If-None-Match: * but map {map_id!r} exists", headers=headers)
        if current is not None and any(weak_match(tag, current) for tag in self.if_none_match or ()):
            raise ApiError(412, f"If-None-Match: map {map_id!r} has the ETag {current}", headers=headers)


async def preconditions(
    request: Request,
    if_match: Annotated[
        str | None,
        Header(
            description="only if the map's current ETag is one of these (strong comparison: a weak "
            'W/"..." tag never matches), or with `*` only if the map exists; else 412 and nothing changes'
        ),
    ] = None,
    if_none_match: Annotated[
        str | None,
        Header(
            description="`*`: only if there is no map of this id (create, never replace); a list of "
            "ETags: only if the map's is none of them (weak comparison); else 412 and nothing changes"
        ),
    ] = None,
) -> Preconditions:
    """The write's preconditions, read from every field line of each header (FastAPI's parameters,
    declared for the spec, hold only the first). 422 for a malformed value."""
    del if_match, if_none_match  # read below, all field lines
    match = joined_field_lines(request.headers, "if-match")
    none_match = joined_field_lines(request.headers, "if-none-match")
    parsed_match = None if match is None else parse_entity_tags(match, "If-Match")
    parsed_none = None if none_match is None else parse_entity_tags(none_match, "If-None-Match")
    return Preconditions(
        if_match=parsed_match,
        match_any=match is not None and parsed_match is None,
        if_none_match=parsed_none,
        none_match_any=none_match is not None and parsed_none is None,
    )


#: A write route's parameter: its `If-Match` / `If-None-Match`, checked by the registry where the
#: write takes effect.
Conditions = Annotated[Preconditions, Depends(preconditions)]
