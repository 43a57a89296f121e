# Idempotent setup shared by bin/stgs and bin/test (sourced, not executed):
# a virtualenv with the pinned requirements (PyAV brings its own FFmpeg with
# libx265 for the project's video I/O), this project installed in it
# (editable), and the native CPU kernels built; for bin/test also Debian's
# ffmpeg binary (when missing and root), which the tests use as an independent
# reader of what the project writes (its DASH demuxer, raw decodes). A second run costs a few hundred milliseconds.

STGS_ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
STGS_VENV=${STGS_VENV:-$STGS_ROOT/.venv}

stgs_die() { echo "stgs setup: $*" >&2; exit 1; }

stgs_has_ffmpeg() {
  command -v ffmpeg >/dev/null 2>&1 && command -v ffprobe >/dev/null 2>&1 || return 1
  # Read the whole list first: `ffmpeg | grep -q` can die of SIGPIPE and fail under pipefail.
  local encoders
  encoders=$(ffmpeg -hide_banner -encoders 2>/dev/null) || return 1
  [[ $encoders == *libx265* ]]
}

stgs_ensure_ffmpeg() {
  stgs_has_ffmpeg && return 0
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "stgs setup: installing ffmpeg (Debian package) ..." >&2
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq ffmpeg; } >/dev/null 2>&1 \
      || stgs_die "apt-get install ffmpeg failed; install ffmpeg with libx265 and retry"
    stgs_has_ffmpeg || stgs_die "the installed ffmpeg lacks libx265; install an ffmpeg built with it"
    return 0
  fi
  stgs_die "ffmpeg and ffprobe with libx265 are required: install them (Debian: sudo apt-get install ffmpeg) and retry"
}

stgs_ensure_venv() {
  local python=${PYTHON:-python3}
  command -v "$python" >/dev/null 2>&1 || stgs_die "python3 (>= 3.11) is required"
  "$python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
    || stgs_die "python3 >= 3.11 is required (found $("$python" --version 2>&1))"
  local want
  want=$(cat "$STGS_ROOT/requirements.lock" "$STGS_ROOT/requirements-ray.lock" "$STGS_ROOT/pyproject.toml" \
    | sha256sum | cut -d' ' -f1)
  if [ -f "$STGS_VENV/.stgs-stamp" ] && [ "$(cat "$STGS_VENV/.stgs-stamp")" = "$want" ]; then
    return 0
  fi
  echo "stgs setup: creating $STGS_VENV with the pinned requirements (first run downloads torch) ..." >&2
  "$python" -m venv "$STGS_VENV" || stgs_die "python3 -m venv failed (Debian: apt-get install python3-venv)"
  # The Ray extra (stgs train/pack --ray) too: the tests start a local Ray cluster.
  # torch from PyPI brings its CUDA libraries: the environment takes about 6.5 GB, and pip's
  # wheel cache would double that, so it is not kept.
  "$STGS_VENV/bin/python" -m pip install -q --disable-pip-version-check --no-cache-dir \
    -r "$STGS_ROOT/requirements.lock" -r "$STGS_ROOT/requirements-ray.lock" \
    || stgs_die "installing requirements.lock and requirements-ray.lock failed (the environment needs about 6.5 GB of free disk)"
  "$STGS_VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e "$STGS_ROOT" \
    || stgs_die "installing streamstgs failed"
  echo "$want" > "$STGS_VENV/.stgs-stamp"
}

stgs_ensure_native() {
  # Without a compiler the project still runs on the pure-torch reference splatter.
  "$STGS_VENV/bin/python" -m stgs.native.build >/dev/null \
    || echo "stgs setup: warning: native kernels not built; using the (slow) pure-torch reference" >&2
}

stgs_ensure_chromium() {
  # Debian's chromium: the browser tests drive it through playwright-core (never a downloaded browser build).
  command -v chromium >/dev/null 2>&1 && return 0
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "stgs setup: installing chromium (Debian package) for the browser tests ..." >&2
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } >/dev/null 2>&1 \
      || echo "stgs setup: apt-get install chromium failed: the browser tests will skip" >&2
    return 0
  fi
  echo "stgs setup: chromium not found: the browser tests will skip (Debian: sudo apt-get install chromium)" >&2
}

stgs_ensure_web() {
  # web/: its npm packages from the lockfile, then the web player's build (web/dist, which `stgs serve` offers at
  # /player/), redone when a source changes. Without Node the player is not built and its tests skip; one line
  # says so.
  if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
    echo "stgs setup: Node.js and npm not found: the web player is not built and its tests skip (Debian: apt-get install nodejs npm)" >&2
    return 0
  fi
  local want
  want=$(cat "$STGS_ROOT/web/package.json" "$STGS_ROOT/web/package-lock.json" | sha256sum | cut -d' ' -f1)
  if [ ! -f "$STGS_ROOT/web/node_modules/.stgs-stamp" ] || [ "$(cat "$STGS_ROOT/web/node_modules/.stgs-stamp")" != "$want" ]; then
    echo "stgs setup: installing web/'s npm packages from its lockfile ..." >&2
    (cd "$STGS_ROOT/web" && npm ci --no-audit --no-fund --loglevel=error >/dev/null) \
      || stgs_die "npm ci in web/ failed"
    echo "$want" > "$STGS_ROOT/web/node_modules/.stgs-stamp"
  fi
  want=$(cd "$STGS_ROOT/web" && cat package-lock.json build.mjs tsconfig.json $(find src -type f | sort) | sha256sum | cut -d' ' -f1)
  if [ -f "$STGS_ROOT/web/dist/.stgs-stamp" ] && [ "$(cat "$STGS_ROOT/web/dist/.stgs-stamp")" = "$want" ]; then
    return 0
  fi
  echo "stgs setup: building the web player (web/dist) ..." >&2
  (cd "$STGS_ROOT/web" && node build.mjs >/dev/null) || stgs_die "building the web player failed (cd web && npm run build)"
  echo "$want" > "$STGS_ROOT/web/dist/.stgs-stamp"
}

stgs_bootstrap() {
  stgs_ensure_venv
  stgs_ensure_native
}
