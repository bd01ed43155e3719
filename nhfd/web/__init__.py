"""The live web view of the bench (`[daemon.web]`, the `web` extra; docs/web.md).

`nhfd.web.server` serves one page and pushes the daemon's state over a WebSocket. It is a client
of the daemon's Unix socket like `nhfctl`, with a fixed list of operations in which arming the
lasers is not: the control plane stays as it is and torch-free, and nothing on the page can arm.
This package's own import pulls in nothing optional; `nhfd.web.server` needs aiohttp.
"""
