"""stgs.server: the async HTTP service for packaged scenes (`stgs serve`).

`config` (settings, types, cache lifetimes), `files` (what a URL path names, never outside ROOT), `responses`
(whole files, ranges and conditionals inside transfer slots; the fast path), `metrics` (Prometheus, access log),
`catalogue` (`/`, `/scenes`), `app` (the assembly), `workers` (one process or several on one port).
"""
