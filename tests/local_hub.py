"""A Hugging Face Hub on localhost: the few routes of the Hub's HTTP API that a push of a model folder uses.

`huggingface_hub` talks to `HF_ENDPOINT`; pointing it here lets a test run a real push, through the real
client and the real command, with no network. Every file is sent as a regular (base64) blob: the server says
so at preupload, so no LFS or Xet transfer is involved. The server keeps what each commit wrote, and answers
any other route with 404 and records it, so that a test sees a request it did not expect.
"""

from __future__ import annotations

import base64
import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlparse


class LocalHub:
    """`with LocalHub() as hub:` serves on a free port; `hub.endpoint` for HF_ENDPOINT, `hub.repos` afterwards:
    repo id -> {path: bytes} of everything committed, `hub.commits` the commit summaries in order."""

    def __init__(self) -> None:
        self.repos: dict[str, dict[str, bytes]] = {}
        self.commits: list[tuple[str, str]] = []
        self.unknown: list[str] = []
        self.tokens: set[str] = set()
        hub = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # quiet: a test reads `hub.unknown` instead
                pass

            def _reply(self, status: int, body: dict) -> None:
                data = json.dumps(body).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def do_POST(self) -> None:
                path = urlparse(self.path).path
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                hub.tokens.add(self.headers.get("authorization", ""))
                if path == "/api/repos/create":
                    request = json.loads(body)
                    owner = request.get("organization") or "user"  # a repo id without owner: the token's user
                    repo_id = f"{owner}/{request['name']}"
                    hub.repos.setdefault(repo_id, {})
                    return self._reply(200, {"url": f"{hub.endpoint}/{repo_id}", "name": repo_id})
                if path == "/api/validate-yaml":
                    return self._reply(200, {"warnings": []})
                parts = path.split("/")  # /api/models/<user>/<name>/<preupload|commit>/<revision>
                if len(parts) == 7 and parts[:3] == ["", "api", "models"]:
                    repo_id, action = f"{parts[3]}/{parts[4]}", parts[5]
                    if repo_id not in hub.repos:
                        return self._reply(404, {"error": f"Repository {repo_id} not found"})
                    if action == "preupload":
                        files = json.loads(body)["files"]
                        modes = [{"path": f["path"], "uploadMode": "regular", "shouldIgnore": False} for f in files]
                        return self._reply(200, {"files": modes})
                    if action == "commit":
                        lines = [json.loads(line) for line in body.decode().splitlines() if line.strip()]
                        for line in lines:
                            if line["key"] == "header":
                                hub.commits.append((repo_id, line["value"]["summary"]))
                            elif line["key"] == "file":
                                content = line["value"]["content"]
                                hub.repos[repo_id][line["value"]["path"]] = base64.b64decode(content)
                            else:  # an LFS pointer or a deletion: this server never asks for them
                                return self._reply(400, {"error": f"unexpected commit item {line['key']}"})
                        oid = f"{len(hub.commits):040x}"
                        url = f"{hub.endpoint}/{repo_id}/commit/{oid}"
                        return self._reply(200, {"commitUrl": url, "commitOid": oid})
                hub.unknown.append(f"POST {path}")
                self._reply(404, {"error": f"no route POST {path}"})

            def do_GET(self) -> None:
                path = urlparse(self.path).path
                if path == "/api/agent-harnesses":  # the client's user-agent registry: an empty one
                    return self._reply(200, {"standardEnvVars": [], "harnesses": {}})
                hub.unknown.append(f"GET {path}")
                self._reply(404, {"error": "not found"})

        self._server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.endpoint = f"http://127.0.0.1:{self._server.server_address[1]}"
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    def __enter__(self) -> LocalHub:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._server.shutdown()
        self._server.server_close()
