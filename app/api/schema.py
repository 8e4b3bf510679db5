"""What the API takes and what its errors look like, checked at the edge so that no request reaches the runner,
the job manager or the database with a value they cannot hold.

- Ids are at most 2^63 - 1 (SQLite's INTEGER), environment ids at most 2^31 - 1 (the simulator's seeds).
- Numbers are finite (JSON's NaN and Infinity, which Python's parser accepts, are refused) and of their own
  type: an integer field takes no `false`, `"70"` or `7e1`.
- Text is valid Unicode (no lone surrogates, which UTF-8 cannot encode) without NUL characters.
- Every error answers {"detail": "<what was wrong>"}; a 422 also lists pydantic's `errors`, made JSON-safe
  (an input that is not plain JSON, such as NaN or a lone surrogate, is left out).
"""

from __future__ import annotations

import math
from typing import Annotated, Any

from fastapi import Path
from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from app.live.commands import MAX_ENV_ID

# the largest integer a JSON reader holds exactly (a double's 53 bits): the schema's maximum is then the number the
# server checks, where 2**63 - 1 (SQLite's INTEGER) read as a double is 2**63, which a schema-valid id could reach
MAX_ID = 2**53 - 1


def _valid_text(value: str) -> str:
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError("must be valid Unicode text (it holds a lone surrogate)") from None
    if "\x00" in value:
        raise ValueError("must not hold a NUL character")
    return value


Text = Annotated[str, AfterValidator(_valid_text)]
EnvId = Annotated[int, Field(ge=0, le=MAX_ENV_ID)]
Id = Annotated[int, Field(ge=1, le=MAX_ID)]


def path_id(what: str) -> Any:
    return Path(ge=1, le=MAX_ID, description=f"the {what}'s id")


class Strict(BaseModel):
    """A request body: no unknown fields, no coercion between types, finite numbers only."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class Error(BaseModel):
    detail: str = Field(description="what was wrong, for people")


class ValidationError(BaseModel):
    detail: str = Field(description="what was wrong, for people; for invalid fields one part per field")
    errors: list[dict] | None = Field(None, description="for invalid fields, pydantic's errors (type, loc, msg; "
                                      "input when it is plain JSON); absent when the request was well formed but "
                                      "cannot be done as asked (an instruction not understood, a file that is not an "
                                      "evaluation)")


def responses(*codes: int) -> dict[int, dict]:
    """OpenAPI entries for the error statuses a route answers with."""
    text = {400: "the body is not what the route reads", 401: "the dashboard's token is missing",
            403: "a wrong token, or a request from another origin", 404: "no such episode, evaluation or run",
            409: "the request does not fit the state (a limit reached, nothing to cancel, no model)",
            413: "the file is too large", 421: "the Host header does not name this dashboard",
            422: "invalid input", 503: "the simulator did not answer in time, or the record cannot be written"}
    return {c: {"model": ValidationError if c == 422 else Error, "description": text[c]} for c in codes}


ACCESS = (401, 403, 421)  # app.api.access, on every route


def plain_errors(errors: list) -> list:
    """Validation errors made JSON-safe: pydantic may put exceptions in 'ctx', NaN or a lone surrogate in 'input'."""
    out = []
    for err in errors:
        err = {k: v for k, v in dict(err).items() if k != "url"}
        if "ctx" in err:
            err["ctx"] = {k: safe_text(str(v)) for k, v in err["ctx"].items()}
        value = err.get("input")
        if not plain(value):
            err.pop("input", None)
        err["loc"] = [x if isinstance(x, int) else safe_text(str(x)) for x in err.get("loc", ())]
        err["msg"] = safe_text(str(err.get("msg", "")))
        out.append(err)
    return out


def plain(value) -> bool:
    """A short JSON scalar that encodes as it is."""
    if value is None or isinstance(value, bool | int):
        return not isinstance(value, int) or abs(value) < 2**63
    if isinstance(value, float):
        return math.isfinite(value)
    return isinstance(value, str) and len(value) <= 200 and safe_text(value) == value


def safe_text(s: str) -> str:
    return s.encode("utf-8", "backslashreplace").decode("utf-8")
