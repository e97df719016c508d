"""What one finished cell sends to the controller and the store keeps (`CellPayload`), as one JSON text, and the
content digest that seals its record (`record_digest`): a stored cell is reused only while it hashes to it."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from .cells import CellRecord, Property
from .errors import InvalidInput


def record_digest(record: Mapping[str, Any]) -> str:
    """sha256 hex of a record's canonical JSON (``CellRecord.to_builtins``: keys sorted, compact, NaN as NaN).
    JSON round-trips these builtins exactly, so a stored record hashes to the digest written beside it unless
    the file was edited."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def record_digests(records: Mapping[str, CellRecord], cells: Sequence[str],
                   known: Mapping[str, str] | None = None) -> dict[str, str]:
    """`payload.record_digest` of each of `cells` that has a record, in that order; those in `known` (checked when
    their records were read) taken as they are, the others hashed."""
    known = known or {}
    return {c: known.get(c) or record_digest(records[c].to_builtins()) for c in cells if c in records}


class RecordDigestMismatch(InvalidInput):
    """A stored cell whose record no longer hashes to its recorded digest: edited or corrupted on disk."""


@dataclass(frozen=True)
class CellPayload:
    """What one finished cell sends to the controller (on the test report under xdist) and the store keeps.

    `key` is the run key a stored result must match to be reused; `properties` the cell's JUnit testcase
    properties; `resumed` says the record was read from the store rather than computed; `recomputed` says why a
    stored record was not reused (its content digest failed), empty otherwise; `stale` names the run-key fields
    in which a stored result of the cell differed, so it was recomputed (e.g. ``dataset_fingerprint``).
    `digest` is the record's `record_digest` when already known: `from_builtins` sets it once it has checked it,
    so whoever reads the payload next (the store, the certificate) does not hash the record again; empty
    otherwise (computed when asked, `record_digest_of`). Not an argument: only `from_builtins` may vouch for
    a digest, and a payload made with ``dataclasses.replace`` (another record, say) starts without one rather
    than carry its source's.
    """

    key: Mapping[str, Any]
    planner: str
    record: CellRecord
    properties: tuple[Property, ...] = ()
    resumed: bool = False
    recomputed: str = ""
    stale: str = ""
    digest: str = field(default="", init=False, compare=False, repr=False)

    @property
    def cell(self) -> str:
        return self.record.cell

    def record_digest_of(self) -> str:
        """`record_digest` of the record: the checked one when `from_builtins` made this payload."""
        return self.digest or record_digest(self.record.to_builtins())

    def to_builtins(self) -> dict[str, Any]:
        """Plain JSON builtins (the store's file; `to_json` of them crosses the xdist boundary)."""
        record = self.record.to_builtins()
        out = {"key": dict(self.key), "planner": self.planner, "record": record,
               "record_digest": self.digest or record_digest(record),
               "properties": [[name, value] for name, value in self.properties], "resumed": self.resumed}
        return {**out, **({"recomputed": self.recomputed} if self.recomputed else {}),
                **({"stale": self.stale} if self.stale else {})}

    @classmethod
    def from_builtins(cls, data: Mapping[str, Any]) -> CellPayload:
        """Inverse of `to_builtins`; `InvalidInput` naming the missing field otherwise, `RecordDigestMismatch` when
        the record does not hash to its ``record_digest`` or has none (a record without a digest cannot be
        checked, so it is never trusted: a digest failure like an edited one)."""
        if not isinstance(data, Mapping):
            raise InvalidInput(f"a cell payload is a JSON object, found {type(data).__name__}")
        try:
            key, planner, record = data["key"], data["planner"], data["record"]
        except KeyError as exc:
            raise InvalidInput(f"cell payload lacks the field {exc.args[0]!r}") from None
        if not isinstance(key, Mapping) or not isinstance(planner, str):
            raise InvalidInput("cell payload: `key` must be an object and `planner` a string")
        recorded = data.get("record_digest")
        if recorded is None and isinstance(record, Mapping):
            raise RecordDigestMismatch(f"cell {record.get('cell')!r}: the stored record has no record_digest, so it "
                                       "cannot be checked: it was edited or written by hand")
        found = record_digest(record) if isinstance(record, Mapping) else None  # not a record: its own error below
        if found is not None and found != recorded:
            raise RecordDigestMismatch(f"cell {record.get('cell')!r}: the stored record hashes to {found[:16]}..., "
                                       f"not to its recorded digest {str(recorded)[:16]}...: it was edited or "
                                       "corrupted on disk")
        props = tuple((str(p[0]), p[1]) for p in data.get("properties", []))
        payload = cls(dict(key), planner, CellRecord.from_builtins(record), props, bool(data.get("resumed", False)),
                      str(data.get("recomputed", "")), str(data.get("stale", "")))
        object.__setattr__(payload, "digest", str(recorded))  # checked above (frozen, and not an argument)
        return payload

    def to_json(self) -> str:
        """The payload as the store's file holds it: what a worker sends the controller, one string (execnet
        copies a string at once, where it walks ten thousand floats one by one in Python: 17 ms a cell to send
        and 11 to receive, against 3 and 2 for this text), and what the controller then writes as it came."""
        return json.dumps(self.to_builtins(), allow_nan=True)

    @classmethod
    def from_json(cls, text: str) -> CellPayload:
        """Inverse of `to_json` (`from_builtins`' checks; `InvalidInput` for text that is not JSON)."""
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise InvalidInput(f"a cell payload is not JSON: {exc}") from None
        return cls.from_builtins(data)
