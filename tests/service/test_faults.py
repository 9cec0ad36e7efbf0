"""Outages told from other errors (``core.faults``): the database's and the store's transient failures, as their
drivers raise them (SQLAlchemy around psycopg and sqlite3, botocore), against a statement the database refuses, a
missing object and a full disk; and ``retrying``'s bounded backoff."""

from __future__ import annotations

import errno
import sqlite3
import time

import pytest
from botocore.exceptions import ClientError, EndpointConnectionError, ReadTimeoutError
from sqlalchemy import create_engine, text
from sqlalchemy.exc import OperationalError

from core.faults import DATABASE, STORAGE, outage_of, retrying


def _client_error(code: str, status: int) -> ClientError:
    return ClientError({"Error": {"Code": code}, "ResponseMetadata": {"HTTPStatusCode": status}}, "PutObject")


def _sqlite_error(sql: str, tmp_path) -> OperationalError:
    engine = create_engine(f"sqlite:///{tmp_path / 'x.db'}")
    with pytest.raises(OperationalError) as info, engine.connect() as conn:
        conn.execute(text(sql))
    return info.value


def test_outages_are_told_by_kind(tmp_path) -> None:
    refused = EndpointConnectionError(endpoint_url="http://127.0.0.1:9")
    assert outage_of(refused).kind == STORAGE  # type: ignore[union-attr]
    assert outage_of(ReadTimeoutError(endpoint_url="http://store")).kind == STORAGE  # type: ignore[union-attr]
    for code, status in (("SlowDown", 503), ("ServiceUnavailable", 503), ("InternalError", 500)):
        assert outage_of(_client_error(code, status)).code == "storage_unavailable"  # type: ignore[union-attr]
    wrapped = RuntimeError("publishing")
    wrapped.__cause__ = refused
    assert outage_of(wrapped).seen == "EndpointConnectionError"  # type: ignore[union-attr]
    down = create_engine("postgresql+psycopg://nobody@127.0.0.1:9/none", connect_args={"connect_timeout": 2})
    with pytest.raises(OperationalError) as info:
        down.connect()
    assert outage_of(info.value).kind == DATABASE  # type: ignore[union-attr]
    locked = OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))
    assert outage_of(locked).code == "database_unavailable"  # type: ignore[union-attr]


def test_other_errors_are_not_outages(tmp_path) -> None:
    assert outage_of(_client_error("NoSuchKey", 404)) is None
    assert outage_of(_client_error("AccessDenied", 403)) is None
    assert outage_of(_sqlite_error("SELECT * FROM no_such_table", tmp_path)) is None  # a refused statement
    assert outage_of(OSError(errno.ENOSPC, "No space left on device")) is None  # full: waiting does not help
    full = OperationalError("INSERT", {}, sqlite3.OperationalError("database or disk is full"))
    full.orig.sqlite_errorcode = sqlite3.SQLITE_FULL  # type: ignore[union-attr]
    assert outage_of(full) is None
    assert outage_of(ValueError("bad")) is None


def test_retrying_waits_out_an_outage_within_its_bound() -> None:
    calls: list[float] = []

    def flaky() -> str:
        calls.append(time.monotonic())
        if len(calls) < 3:
            raise EndpointConnectionError(endpoint_url="http://store")
        return "done"

    assert retrying(flaky, within=10, doing="test", first=0.05) == "done" and len(calls) == 3

    def down() -> None:
        raise EndpointConnectionError(endpoint_url="http://store")

    t0 = time.monotonic()
    with pytest.raises(EndpointConnectionError):
        retrying(down, within=0.5, doing="test", first=0.05)
    assert 0.4 <= time.monotonic() - t0 < 2.0

    def broken() -> None:
        calls.append(0.0)
        raise ValueError("not an outage")

    calls.clear()
    with pytest.raises(ValueError):
        retrying(broken, within=10, doing="test", first=0.05)
    assert len(calls) == 1  # raised at once
