# stgs serve: the streaming server only (aiohttp, lxml, prometheus-client; no torch), with the web player at
# /player/ (built in a Node stage from web/'s lockfile; only its dist/ reaches the image).
# Build from the repository root:  docker build -f docker/server.Dockerfile -t streamstgs-server .
# Run:  docker run -p 8080:8080 -v /path/to/packaged/scenes:/data:ro streamstgs-server
FROM node:20-slim AS web
WORKDIR /web
COPY web/package.json web/package-lock.json ./
RUN npm ci --no-audit --no-fund --loglevel=error
COPY web/build.mjs web/tsconfig.json ./
COPY web/src ./src
RUN node build.mjs

FROM python:3.11-slim

WORKDIR /app
COPY requirements.lock pyproject.toml README.md ./
COPY stgs ./stgs
COPY --from=web /web/dist ./web/dist
# The server's slice of requirements.lock, at exactly the versions the README's setup installs.
RUN grep -E '^(aiohttp|aiohappyeyeballs|aiosignal|attrs|frozenlist|multidict|propcache|yarl|idna|typing_extensions|lxml|prometheus_client)==' \
        requirements.lock > server-requirements.txt \
    && pip install --no-cache-dir --no-deps -r server-requirements.txt \
    && pip install --no-cache-dir --no-deps . \
    && useradd --create-home --uid 10001 stgs

USER stgs
VOLUME ["/data"]
EXPOSE 8080
HEALTHCHECK --interval=15s --timeout=3s --start-period=5s --retries=3 \
    CMD python -c "import urllib.request,sys; sys.exit(urllib.request.urlopen('http://127.0.0.1:8080/healthz', timeout=2).status != 200)"
STOPSIGNAL SIGTERM
ENTRYPOINT ["stgs", "serve"]
# Given more than one core, add "--workers", "N" (processes sharing the port; /metrics sums them).
CMD ["/data", "--host", "0.0.0.0", "--port", "8080", "--player-dir", "/app/web/dist"]
