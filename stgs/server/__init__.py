"""stgs.server: the async HTTP service for packaged scenes (`stgs serve`).

`config` (settings, types, cache lifetimes), `files` (what a URL path names, never outside ROOT), `decide`
(200/206/304/412/416 from the headers and the file's stat, before any I/O), `responses` (FileTransfer does the
I/O inside a transfer slot; the fast path), `metrics` (Prometheus, access log), `catalogue` (`/`, `/scenes`),
`app` (the assembly), `workers` (one process or several on one port).
"""
