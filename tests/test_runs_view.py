"""The MLflow app plugin behind scripts/mlflow_ui.sh (mlflow_plugins/nrbench_runs_view): MLflow's own app
whose page stores the "Model training" view in a browser that has not picked one. Driven here through ASGI
against MLflow's real app; what a browser does with the page: tests/test_mlflow_ui.py (slow)."""

import asyncio
import importlib.metadata
import json
from pathlib import Path

import mlflow.server
import pytest
from nrbench_runs_view import (
    RUNS_VIEW,
    VIEW_KEY,
    RunsViewApp,
    app,
    default_view_script,
    with_default_view,
)

MLFLOW_PAGE = (Path(mlflow.server.app.static_folder) / "index.html").read_bytes()


def _request(asgi, path="/", method="GET"):
    """(status, headers as a dict of lower-case names, body) of one request to `asgi`."""
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": method,
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "root_path": "",
        "query_string": b"",
        "headers": [(b"host", b"127.0.0.1:5000")],
        "client": ("127.0.0.1", 50000),
        "server": ("127.0.0.1", 5000),
    }
    sent = []

    async def receive():
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message):
        sent.append(message)

    asyncio.run(asgi(scope, receive, send))
    start = next(m for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    headers = {name.decode().lower(): value.decode() for name, value in start["headers"]}
    return start["status"], headers, body


def test_mlflow_finds_the_app_by_its_entry_point():
    (entry,) = {e for e in importlib.metadata.entry_points(group="mlflow.app") if e.name == "nrbench"}
    assert entry.load() is app
    assert not callable(getattr(app, "__code__", None))  # an instance: MLflow starts a function as a factory


def test_the_script_stores_model_training_under_mlflows_key_only_when_unset():
    script = default_view_script().decode()
    assert (VIEW_KEY, RUNS_VIEW) == ("mlflow.workflowType_v1", "machine_learning")
    # the value is what MLflow's useLocalStorage writes: the JSON of the string
    assert f'localStorage.setItem("{VIEW_KEY}",{json.dumps(json.dumps(RUNS_VIEW))})' in script
    assert f'if(localStorage.getItem("{VIEW_KEY}")===null)' in script
    other = default_view_script("k", "genai").decode()
    assert 'getItem("k")' in other and 'setItem("k","\\"genai\\"")' in other


def test_the_script_goes_first_in_the_head_and_a_page_without_a_head_is_left_alone():
    page = b"<!doctype html><html><head><script src=main.js></script></head><body></body></html>"
    assert with_default_view(page) == page.replace(b"<head>", b"<head>" + default_view_script())
    assert with_default_view(b"<html><body>no head</body></html>") == b"<html><body>no head</body></html>"
    assert with_default_view(b"<head></head>") == b"<head>" + default_view_script() + b"</head>"  # at 0


def test_mlflows_page_gets_the_script_with_its_length_and_without_its_validators():
    status, headers, body = _request(app)
    assert status == 200 and headers["content-type"].startswith("text/html")
    assert body == with_default_view(MLFLOW_PAGE) and body != MLFLOW_PAGE
    assert body.index(default_view_script()) < body.index(b"<script", body.index(default_view_script()) + 1)
    assert int(headers["content-length"]) == len(body)
    assert "etag" not in headers and "last-modified" not in headers
    assert headers["x-content-type-options"] == "nosniff"  # MLflow's own middleware still answered
    plain_status, plain_headers, plain = _request(mlflow.server.fastapi_app.app)
    assert (plain_status, plain) == (200, MLFLOW_PAGE) and "last-modified" in plain_headers


@pytest.mark.parametrize(("path", "method"), [("/favicon.ico", "GET"), ("/", "HEAD"), ("/health", "GET")])
def test_every_other_request_is_mlflows_answer_unchanged(path, method):
    ours, theirs = _request(app, path, method), _request(mlflow.server.fastapi_app.app, path, method)
    assert ours[0] == theirs[0] and ours[2] == theirs[2]
    ours[1].pop("date", None), theirs[1].pop("date", None)
    assert ours[1] == theirs[1]


def _stub(status, content_type, chunks, extra_headers=()):
    """An ASGI app answering every request with `chunks` as a streamed body (its last message without
    `more_body`, which ASGI then reads as false)."""

    async def inner(scope, receive, send):
        headers = [(b"content-type", content_type), (b"etag", b'"v1"'), *extra_headers]
        await send({"type": "http.response.start", "status": status, "headers": headers})
        for chunk in chunks[:-1]:
            await send({"type": "http.response.body", "body": chunk, "more_body": True})
        await send({"type": "http.response.body", "body": chunks[-1]})

    return inner


def test_a_scope_other_than_http_goes_to_mlflows_app_untouched():
    seen = []

    async def inner(scope, receive, send):
        seen.append(scope)

    lifespan = {"type": "lifespan", "asgi": {"version": "3.0"}}
    asyncio.run(RunsViewApp(inner)(lifespan, None, None))
    assert seen == [lifespan]


def test_a_streamed_page_is_joined_before_the_rewrite():
    streamed = _stub(200, b"text/html; charset=utf-8", [b"<html><he", b"ad>x"])
    status, headers, body = _request(RunsViewApp(streamed))
    assert (status, body) == (200, b"<html><head>" + default_view_script() + b"x")
    assert headers["content-length"] == str(len(body)) and "etag" not in headers


def test_a_message_after_the_body_passes_after_the_rewritten_page():
    async def with_trailers(scope, receive, send):
        await send(
            {"type": "http.response.start", "status": 200, "headers": [(b"content-type", b"text/html")]}
        )
        await send({"type": "http.response.body", "body": b"<head>"})
        await send({"type": "http.response.trailers", "headers": [], "more_trailers": False})

    sent = []

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "path": "/", "method": "GET"}
    asyncio.run(RunsViewApp(with_trailers)(scope, None, send))
    assert [m["type"] for m in sent] == [
        "http.response.start",
        "http.response.body",
        "http.response.trailers",
    ]
    assert sent[1]["body"] == b"<head>" + default_view_script()


@pytest.mark.parametrize(
    ("status", "content_type"),
    [(304, b"text/html"), (403, b"text/html"), (200, b"application/json"), (200, b"text/plain")],
)
def test_a_response_that_is_not_the_page_passes_with_its_headers(status, content_type):
    got = _request(RunsViewApp(_stub(status, content_type, [b"<head>", b"x"], [(b"content-length", b"7")])))
    headers = {"content-type": content_type.decode(), "etag": '"v1"', "content-length": "7"}
    assert got == (status, headers, b"<head>x")
