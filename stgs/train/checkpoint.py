"""Training checkpoints: model, the modules trained beside it (auxiliary transformer, camera colours), Adam state,
opacity accumulator and random generator in one safetensors file per stage (no pickle), the stage's progress in
its JSON metadata, written atomically."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from stgs.model.gop import GOPModel
from stgs.train.ops import Optimizer


def module_tensors(prefix: str, module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """`module`'s state as tensors named `prefix.KEY` (what `under(tensors, prefix)` gives back)."""
    return {f"{prefix}.{k}": v.detach().contiguous() for k, v in module.state_dict().items()}


def under(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors named `prefix.KEY`, by KEY."""
    start = len(prefix) + 1
    return {k[start:]: v for k, v in tensors.items() if k.startswith(f"{prefix}.")}


class Checkpoints:
    """The checkpoints of one run in `folder`; `resume` says whether loading one is wanted at all."""

    def __init__(self, folder: Path, resume: bool):
        self.folder, self.resume = folder, resume

    def path(self, name: str) -> Path:
        return self.folder / f"{name}.safetensors"

    def save(self, name: str, model: GOPModel, opt: Optimizer, gen: torch.Generator, extra: dict,
             modules: dict[str, torch.nn.Module | None] | None = None, accum: torch.Tensor | None = None) -> None:
        """`modules`: the modules trained beside the model, by name (None values are skipped)."""
        tensors = module_tensors("model", model)
        for prefix, module in (modules or {}).items():
            if module is not None:
                tensors |= module_tensors(prefix, module)
        for group in opt.opt.param_groups:
            for i, p in enumerate(group["params"]):
                for key, t in opt.opt.state.get(p, {}).items():
                    if torch.is_tensor(t):
                        tensors[f"adam.{group['name']}.{i}.{key}"] = t.detach().reshape(t.shape).contiguous()
        if accum is not None:
            tensors["accum"] = accum.contiguous()
        tensors["rng"] = gen.get_state()
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.path(name)
        tmp = path.with_suffix(".tmp")
        save_file(tensors, str(tmp), metadata={"state": json.dumps(extra)})
        tmp.replace(path)

    def load(self, name: str, model: GOPModel, opt: Optimizer, gen: torch.Generator,
             modules: dict[str, torch.nn.Module | None] | None = None) -> tuple[dict, torch.Tensor | None] | None:
        """Restore `name` into model, `modules`, opt and `gen`; (its extra, its accumulator), or None when
        not resuming or there is no such checkpoint."""
        path = self.path(name)
        if not (self.resume and path.is_file()):
            return None
        with safe_open(str(path), "pt") as f:
            extra = json.loads(f.metadata()["state"])
        tensors = load_file(str(path))
        model.load_state_dict(under(tensors, "model"))
        for prefix, module in (modules or {}).items():
            if module is not None:
                module.load_state_dict(under(tensors, prefix))
        for group in opt.opt.param_groups:
            for i, p in enumerate(group["params"]):
                if state := under(tensors, f"adam.{group['name']}.{i}"):
                    opt.opt.state[p] = state
        gen.set_state(tensors["rng"])
        return extra, tensors.get("accum")
