"""One contract, two implementations: the page's caps and ABR rules are held to the Python ones, the rules by
decision vectors the simulator records (stgs.harness.vectors) and the TypeScript ports replay under Node."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess

from stgs import limits
from stgs.client.abr import AbrSettings
from stgs.harness.vectors import FIXED_TRACES, MPC_VARIANTS, decision_vectors, settings_json
from tests.web.conftest import DIST, NODE, WEB, need_node


def test_the_pages_caps_are_the_python_caps():
    text = (WEB / "src" / "limits.ts").read_text()
    ours = {m[1]: float(m[2]) for m in re.finditer(r"export const (\w+) = ([\d.]+);", text)}
    shared = {k: v for k, v in ours.items() if hasattr(limits, k)}
    assert len(shared) >= 15
    assert {k: float(getattr(limits, k)) for k in shared} == shared


def test_the_pages_poster_path_rule_is_the_catalogues():
    from stgs.server.catalogue import POSTER_PATH

    text = (WEB / "src" / "scene.ts").read_text()
    ours = re.search(r"const POSTER_PATH = /\^(.*)\$/;", text)[1].replace("\\/", "/")
    assert ours == POSTER_PATH.pattern


def test_the_pages_view_frustum_is_the_python_one():
    from stgs.model import renderer

    text = (WEB / "src" / "sort.ts").read_text()
    ours = {m[1]: float(m[2]) for m in re.finditer(r"export const (NEAR_CLIP|GUARD_BAND) = ([\d.]+);", text)}
    assert ours == {"NEAR_CLIP": renderer.NEAR_CLIP, "GUARD_BAND": renderer.GUARD_BAND}


def test_the_keyframe_quantisations_are_the_python_ones():
    from stgs.codec.quant import FLOAT_FIELD_BITS, LOSSLESS, MAX_FIELD_BITS

    text = (WEB / "src" / "container.ts").read_text()
    lossless = re.search(r"export const LOSSLESS: KeyframeQuant = \{([^}]*)\}", text)[1]
    fields = dict(re.findall(r"(\w+): (\w+)", lossless))
    consts = {m[1]: int(m[2]) for m in re.finditer(r"export const (FLOAT_FIELD_BITS|MAX_FIELD_BITS) = (\d+);", text)}
    assert consts == {"FLOAT_FIELD_BITS": FLOAT_FIELD_BITS, "MAX_FIELD_BITS": MAX_FIELD_BITS}
    values = {k: int(v) if v.isdigit() else consts[v] for k, v in fields.items()}
    assert values == dataclasses.asdict(LOSSLESS)


def test_the_abr_defaults_are_the_python_defaults():
    need_node()
    out = subprocess.run([NODE, "--input-type=module", "-e",
                          f"import {{ DEFAULT_SETTINGS }} from '{DIST / 'node' / 'abr.mjs'}'; "
                          "process.stdout.write(JSON.stringify(DEFAULT_SETTINGS))"],
                         capture_output=True, text=True, timeout=60, check=True)
    python = settings_json(AbrSettings())
    python.pop("abandonMinS")  # the page does not abandon downloads
    assert json.loads(out.stdout) == python


def test_the_pages_abr_rules_replay_the_simulators_decisions(web_root, tmp_path):
    need_node()
    vectors = decision_vectors(web_root / "small")
    assert len(vectors) == (5 + len(MPC_VARIANTS)) * len(FIXED_TRACES)
    rungs = {s["decision"]["index"] for v in vectors for s in v["steps"]}
    deciders = {s["decision"]["rule"] for v in vectors for s in v["steps"]}
    assert rungs == {0, 1, 2}  # the vectors cross the whole ladder ...
    assert {"mpc", "throughput", "bola", "bola-e", "insufficient-buffer"} <= deciders  # ... and every rule decides
    mpc = [((v["settings"]["mpcPredictor"], v["settings"]["mpcBufferConstraint"], v["settings"]["mpcUtility"]),
            v["scenario"], tuple(s["decision"]["index"] for s in v["steps"])) for v in vectors if v["rule"] == "mpc"]
    # each predictor, buffer mode and utility is replayed, and they plan differently somewhere
    assert len({setting for setting, _, _ in mpc}) == 1 + len(MPC_VARIANTS)
    assert len({(name, rungs) for _, name, rungs in mpc}) > len(FIXED_TRACES)
    path = tmp_path / "vectors.json"
    path.write_text(json.dumps({"vectors": vectors}))
    out = subprocess.run([NODE, str(WEB / "tools" / "abr-replay.mjs"), str(path)], capture_output=True, text=True,
                         timeout=120, check=True)
    replays = [json.loads(line) for line in out.stdout.splitlines()]
    assert [(r["rule"], r["scenario"], r["steps"]) for r in replays] == \
        [(v["rule"], v["scenario"], len(v["steps"])) for v in vectors]
    assert [m for r in replays for m in r["mismatches"]] == []
