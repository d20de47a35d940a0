"""MLflow's own server app, with one change: a browser that has not picked a view opens experiments on their
runs.

MLflow 3.17's UI decides an experiment's page from its sidebar switch "GenAI | Model training", which it
keeps in the browser's localStorage under `mlflow.workflowType_v1` (a JSON string, "genai" or
"machine_learning"; unset means GenAI), not from the experiment (upstream mlflow/mlflow#24498). So in a
fresh browser every experiment opens on the GenAI overview ("Traces 0"). Every page of the UI is the one
`index.html` served at `/` (the UI's routes follow '#'); here its `<head>` starts with a script that stores
"machine_learning" when the key is unset. A browser that picked GenAI keeps GenAI.

Started by `mlflow ui --app-name nrbench` (scripts/mlflow_ui.sh), which sets up the tracking store exactly
as for MLflow's default app and serves this one instead.
"""

import json

from mlflow.server.fastapi_app import app as mlflow_app

VIEW_KEY = "mlflow.workflowType_v1"  # MLflow's useLocalStorage({key: "mlflow.workflowType", version: 1})
RUNS_VIEW = "machine_learning"  # the switch's "Model training"
PAGE_PATH = "/"


def default_view_script(key: str = VIEW_KEY, view: str = RUNS_VIEW) -> bytes:
    """A script storing `view` under `key` unless the browser holds a value (a private window may refuse
    storage: then MLflow's own default stays)."""
    key_js, value_js = json.dumps(key), json.dumps(json.dumps(view))
    return (
        f"<script>try{{if(localStorage.getItem({key_js})===null)"
        f"localStorage.setItem({key_js},{value_js})}}catch(e){{}}</script>"
    ).encode()


def with_default_view(page: bytes) -> bytes:
    """`page` with `default_view_script()` first in its `<head>` (before MLflow's own scripts read the key);
    a page without `<head>` comes back unchanged."""
    head = page.find(b"<head>")
    if head < 0:
        return page
    end = head + len(b"<head>")
    return page[:end] + default_view_script() + page[end:]


def _is_full_html(start: dict) -> bool:
    headers = {name.lower(): value for name, value in start.get("headers", [])}
    return start["status"] == 200 and headers.get(b"content-type", b"").startswith(b"text/html")


class RunsViewApp:
    """ASGI: the app `inner` (MLflow's), with its response to `GET /` buffered (a ~2 kB page) and rewritten
    by `with_default_view`. The rewritten page's validators (ETag, Last-Modified) are dropped so that no
    cache answers with the unmodified page, and its length is set to the new body's. An instance, not a
    function: MLflow starts a plain function as an app factory."""

    def __init__(self, inner):
        self.inner = inner

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["path"] != PAGE_PATH or scope["method"] != "GET":
            await self.inner(scope, receive, send)
            return
        start: dict = {}
        chunks: list[bytes] = []

        async def rewrite(message):
            if message["type"] == "http.response.start":
                start.update(message)
                return
            if message["type"] != "http.response.body":
                await send(message)
                return
            chunks.append(message.get("body", b""))
            if message.get("more_body", False):
                return
            body = b"".join(chunks)
            headers = list(start.get("headers", []))
            if _is_full_html(start):
                body = with_default_view(body)
                dropped = {b"content-length", b"etag", b"last-modified"}
                headers = [(k, v) for k, v in headers if k.lower() not in dropped]
                headers.append((b"content-length", str(len(body)).encode()))
            await send({**start, "headers": headers})
            await send({"type": "http.response.body", "body": body})

        await self.inner(scope, receive, rewrite)


app = RunsViewApp(mlflow_app)
