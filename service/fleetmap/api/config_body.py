"""The body of `PUT /maps/{map_id}`: a map configuration, validated as a new one, which may also be
the configuration of a map stored before one of today's limits.

A map stored so keeps loading with its configuration (`fleetmap.config.STORED_CONFIG`), and `GET`
answers it. `PUT` of that configuration, as a provisioning script sends at every start, is that map
again (200, nothing changed); refused as a new configuration, it was a 422 after every upgrade. For
any other map (none of that id, or one of another configuration) it is still refused with the 422 a
new configuration past a limit gets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError, ValidatorFunctionWrapHandler, WrapValidator
from pydantic_core import PydanticCustomError

from fleetmap.config import STORED_CONFIG, TRIED_AS_STORED, MapConfig
from fleetmap.map_entry import Expectation, MapEntry


@dataclass(frozen=True)
class PastTodaysLimits:
    """A body refused as a new configuration (`errors`, located in the body as FastAPI locates
    them) that is valid as a stored one (`config`)."""

    config: MapConfig
    errors: list[dict[str, Any]]

    def only_as_its_map(self, then: Expectation | None) -> Expectation:
        """The registry's check (`MapRegistry.create`'s `expect`, under its lock) that the map of the
        id has this configuration (`MapConfig.same_map_as`), else the 422 of a new one; then `then`
        (the request's conditions), which come after the request's own validation."""

        def expect(existing: MapEntry | None) -> None:
            if existing is None or not existing.config.same_map_as(self.config):
                raise RequestValidationError(self.errors)
            if then is not None:
                then(existing)

        return expect


def _or_past_todays_limits(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
    """`value` as a new configuration, or, refused so but valid as a stored one, `PastTodaysLimits`.
    A JSON null is refused saying what to send instead (FastAPI gives the route its default, the
    server's configuration, only for no body at all)."""
    if value is None:
        raise PydanticCustomError(
            "dict_type",
            "a map configuration is a JSON object, not null; send no body for the server's default",
        )
    try:
        return handler(value)
    except ValidationError as refused:
        try:
            stored = MapConfig.model_validate(value, context={STORED_CONFIG: True, TRIED_AS_STORED: True})
        except ValidationError:
            raise refused from None
        errors = [{**e, "loc": ("body", *e["loc"])} for e in refused.errors(include_url=False)]
        return PastTodaysLimits(stored, errors)


#: `PUT /maps/{map_id}`'s body: a `MapConfig` (its schema in the spec), or `PastTodaysLimits`, which
#: the route must resolve (`PastTodaysLimits.only_as_its_map`) before it makes anything of it.
MapConfigBody = Annotated[MapConfig, WrapValidator(_or_past_todays_limits)]
