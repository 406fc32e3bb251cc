"""Training recipes: a policy trained in stages from scratch by one command
(``rl train --recipe NAME --seed N --out DIR``).

A recipe (``configs/recipes/NAME.toml``) names its stages in order, each an ``rl train``
config (a path from the repository's root, as the configs name their data files) and, for a
stage after the first, the earlier stage whose ``best/`` it starts from::

    description = "..."
    batch_workers = 2          # processes the batched simulator is split over (the same rollouts)

    [[stage]]
    name = "stage1"
    config = "configs/....toml"

    [[stage]]
    name = "stage2"
    config = "configs/....toml"
    init_from = "stage1"

Every stage trains with the recipe's seed. ``best/`` of a run is the checkpoint that scored
best on the run's own periodic evaluation (the config's ``select_best`` rule over
``eval_episodes`` episodes from the fixed evaluation seed ``rl.train.session.EVAL_SEED``), never on
held-out episodes: selecting with the episodes a policy is later reported on would flatter it.

The output folder ``DIR``::

    recipe.json                    the recipe, seed, stages and their state (resumable)
    runs/<stage>/                  each stage's run folder (``rl train``'s: checkpoints, best/)
    model.json, weights.npz        the last stage's best/: the recipe's policy (``rl eval
    config.toml, provenance.json     --policy DIR``), as a shipped policy folder is laid out
    eval_history.jsonl, checksums.sha256
    <stage>/                       each earlier stage's best/ with its records, likewise

Run again with the same arguments after an interruption (SIGINT, SIGTERM, SIGKILL), the recipe
goes on where it stopped: a finished stage is kept, the running one resumes from its newest
checkpoint (the same weights as a run never stopped, ``rl.train.training``). Another recipe or seed
in the same folder is refused, and so is the same recipe once its stages, their configs or the
content of the data files they read have changed (comments and the description may change).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from uwdock.dockcore.config import (
    dumps_toml,
    from_dict,
    load_config,
    replace_at,
    to_dict,
    validated,
)
from uwdock.dockcore.domains import Interval
from uwdock.dockcore.errors import DockError
from uwdock.dockcore.io import atomic_write_files, atomic_write_json
from uwdock.rl.env.config import EnvConfig, env_input_files, with_input_files
from uwdock.rl.train.training import TrainConfig, train

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: The repository's root: recipes, their stage configs and the data files those name.
ROOT = Path(__file__).resolve().parents[2]
#: Where the recipes are.
RECIPES = ROOT / "configs" / "recipes"
#: The files of a stage's policy copied into the recipe's folder (the shipped layout).
POLICY_FILES = ("model.json", "weights.npz")
RECORD_FILES = ("config.toml", "provenance.json", "eval_history.jsonl")
STATE = "recipe.json"


@dataclass(frozen=True)
class Stage:
    """One stage of a recipe.

    Attributes:
        name: its name (its run folder ``runs/<name>``; letters, digits, ``_`` and ``-``).
        config: its ``rl train`` config, from the repository's root.
        init_from: the earlier stage whose ``best/`` it starts from (None: from scratch).
    """

    name: str
    config: str
    init_from: str | None = None

    def validate(self) -> None:
        if not self.name or not all(c.isalnum() or c in "_-" for c in self.name):
            raise ValueError(f"stage name {self.name!r}: letters, digits, '_' and '-' only")
        if self.name in ("runs",) or self.name.startswith("."):
            raise ValueError(f"stage name {self.name!r} is reserved")


@dataclass(frozen=True)
class Recipe:
    """A recipe (module docstring).

    Attributes:
        description: one paragraph.
        stages: in the order they train.
        batch_workers: processes the batched simulator is split over (``rl train
            --batch-workers``; the same rollouts with any count).
    """

    description: str = ""
    stages: tuple[Stage, ...] = ()
    batch_workers: Annotated[int, Interval(ge=1, le=64)] = 1

    def validate(self) -> None:
        if not self.stages:
            raise ValueError("a recipe needs at least one [[stage]]")
        seen: list[str] = []
        for stage in self.stages:
            if stage.name in seen:
                raise ValueError(f"stage {stage.name!r} is named twice")
            if stage.init_from is not None and stage.init_from not in seen:
                raise ValueError(
                    f"stage {stage.name!r} starts from {stage.init_from!r}, which is not an "
                    "earlier stage"
                )
            seen.append(stage.name)


def recipe_names() -> list[str]:
    """The recipes shipped (``configs/recipes/*.toml``), sorted."""
    return sorted(p.stem for p in RECIPES.glob("*.toml")) if RECIPES.is_dir() else []


def load_recipe(name: str) -> tuple[Recipe, dict[str, TrainConfig], str]:
    """The recipe ``name``, each stage's config (its data files named from the repository's
    root) and the recipe's content digest (:func:`_content_digest`).

    Raises:
        DockError: an unknown recipe (the line lists the shipped ones), a malformed one, a
            stage config that is missing or bad.
    """
    path = RECIPES / f"{name}.toml"
    if name not in recipe_names():
        known = ", ".join(recipe_names()) or "none"
        raise DockError(f"no recipe {name!r}: the recipes are {known} ({RECIPES})")
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise DockError(f"recipe {path}: {exc}") from None
    data["stages"] = data.pop("stage", [])
    try:
        recipe = from_dict(Recipe, data)
    except (TypeError, ValueError) as exc:
        raise DockError(f"recipe {path}: {exc}") from None
    loaded: dict[str, TrainConfig] = {}
    for stage in recipe.stages:
        config = ROOT / stage.config
        if not config.is_file():
            raise DockError(f"recipe {name}: stage {stage.name}: {config}: no such file")
        loaded[stage.name] = load_config(TrainConfig, config, section="train")
    configs = {k: _inputs_from_root(cfg) for k, cfg in loaded.items()}
    return recipe, configs, _content_digest(recipe, loaded, configs)


def _content_digest(
    recipe: Recipe, loaded: dict[str, TrainConfig], resolved: dict[str, TrainConfig]
) -> str:
    """What makes two trainings of a recipe the same: its stages (names, order, what each starts
    from), their configs as loaded (paths as written), and the content of the data files they
    read; not where the stage configs live, how they are split into files (``extends``), their
    comments, the description or ``batch_workers`` (the same rollouts with any count)."""
    inputs: dict[str, str] = {}
    for name, cfg in resolved.items():
        written = env_input_files(loaded[name].env)
        for key, path in env_input_files(cfg.env).items():
            try:
                inputs[written[key]] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
            except OSError as exc:
                raise DockError(f"recipe stage {name}: {path}: {exc.strerror or exc}") from None
    blob = {
        "stages": [
            {k: v for k, v in dataclasses.asdict(s).items() if k != "config"} for s in recipe.stages
        ],
        "configs": {k: to_dict(v) for k, v in loaded.items()},
        "inputs": inputs,
    }
    return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()


def _inputs_from_root(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` with its env's relative input paths taken from the repository's root (where a
    recipe's configs name them from), so the recipe runs from any working directory."""
    env = with_input_files(cfg.env, lambda p: p if Path(p).is_absolute() else str(ROOT / p))
    return validated(dataclasses.replace(cfg, env=env))


def _state(name: str, seed: int, digest: str, recipe: Recipe) -> dict[str, Any]:
    return {
        "recipe": name,
        "seed": seed,
        "recipe_sha256": digest,
        "stages": [
            {k: v for k, v in dataclasses.asdict(s).items() if k != "config"} for s in recipe.stages
        ],
        "done": [],
    }


def _check_folder(out: Path, state: dict[str, Any]) -> dict[str, Any]:
    """The folder's recorded state, or ``state`` for a new folder; another recipe, seed or
    recipe content there is refused."""
    path = out / STATE
    if not path.is_file():
        if out.is_dir() and any(p for p in out.iterdir() if not p.name.startswith(".")):
            raise DockError(f"{out} holds other files: a recipe needs a new or its own folder")
        return state
    try:
        old = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DockError(f"{path}: cannot read it ({exc})") from None
    if not isinstance(old, dict) or (old.get("recipe"), old.get("seed")) != (
        state["recipe"],
        state["seed"],
    ):
        was = (
            f"recipe {old.get('recipe')}, seed {old.get('seed')}" if isinstance(old, dict) else "?"
        )
        raise DockError(f"{out} holds another recipe run ({was}): use another --out")
    if old.get("recipe_sha256") != state["recipe_sha256"]:
        raise DockError(
            f"{out} was trained with another version of the recipe (its stages, their configs "
            "or the data files they read changed since): use another --out"
        )
    done = [d for d in old.get("done", []) if isinstance(d, str)]
    return {**state, "recipe_sha256": old["recipe_sha256"], "done": done}


def run_recipe(
    name: str,
    seed: int,
    out_dir: str | os.PathLike[str],
    note: Callable[[str], None] = lambda _m: None,
    progress: bool = True,
    batch_workers: int | None = None,
    backend: str = "local",
    ray_address: str | None = None,
) -> Path:
    """Train (or resume) recipe ``name`` with ``seed`` into ``out_dir`` (module docstring);
    returns the folder, which then holds the recipe's policy."""
    recipe, configs, digest = load_recipe(name)
    out = Path(out_dir)
    state = _check_folder(out, _state(name, seed, digest, recipe))
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / STATE, state)
    workers = recipe.batch_workers if batch_workers is None else batch_workers
    n = len(recipe.stages)
    for k, stage in enumerate(recipe.stages, 1):
        run = out / "runs" / stage.name
        if stage.name in state["done"] and (run / "best" / "weights.npz").is_file():
            # trained: nothing to check against the config (its data files may now be named
            # from another checkout; their content is in the recipe's digest)
            note(f"recipe {name}, seed {seed}: stage {k}/{n} {stage.name}: done ({run})")
            continue
        cfg = dataclasses.replace(configs[stage.name], seed=seed)
        resume = (run / "config.toml").is_file()
        init = None
        if stage.init_from is not None and not resume:
            init = str(out / "runs" / stage.init_from / "best")
        how = (
            "resuming" if resume else f"from {stage.init_from}'s best/" if init else "from scratch"
        )
        note(f"recipe {name}, seed {seed}: stage {k}/{n} {stage.name} ({cfg.total_steps:,} "
             f"steps, {how}) into {run}")  # fmt: skip
        train(cfg, run, resume=resume, init_policy=init, progress=progress, note=note,
              backend=backend, ray_address=ray_address, batch_workers=workers)  # fmt: skip
        if stage.name not in state["done"]:
            state["done"].append(stage.name)
            atomic_write_json(out / STATE, state)
    for k, stage in enumerate(recipe.stages, 1):
        dest = out if k == n else out / stage.name
        named = load_config(TrainConfig, ROOT / stage.config, section="train").env
        _publish(out / "runs" / stage.name, dest, env_input_files(named))
    note(f"recipe {name}, seed {seed}: the policy is {out} (rl eval --policy {out})")
    return out


def _publish(run: Path, dest: Path, named: dict[tuple[str, ...], str]) -> None:
    """A run's ``best/`` policy and its records into ``dest`` with ``checksums.sha256`` of the
    policy files (the layout of ``rl/policies/*``), written as one unit. Its ``config.toml``
    names the data files as the stage's config does (``named``: by field path) where the run
    read that file of a checkout (:func:`_as_named`), so the folder works in any checkout,
    moved or shipped."""
    best = run / "best"
    dest.mkdir(parents=True, exist_ok=True)
    files = {dest / name: (best / name).read_bytes() for name in POLICY_FILES}
    sums = "".join(f"{hashlib.sha256(d).hexdigest()}  {p.name}\n" for p, d in files.items())
    files.update({dest / n: (run / n).read_bytes() for n in RECORD_FILES if (run / n).is_file()})
    if (run / "config.toml").is_file():
        cfg = load_config(TrainConfig, run / "config.toml", section="train")
        cfg = dataclasses.replace(cfg, env=_as_named(cfg.env, named))
        files[dest / "config.toml"] = dumps_toml({"train": cfg}).encode()
    files[dest / "checksums.sha256"] = sums.encode()
    atomic_write_files(files)


def _as_named(env: EnvConfig, named: dict[tuple[str, ...], str]) -> EnvConfig:
    """``env`` with each absolute input file that is the config's relative name taken from
    some checkout's root (:func:`_inputs_from_root`) named as the config names it."""
    for path, value in env_input_files(env).items():
        rel = Path(named.get(path, ""))
        if named.get(path) and not rel.is_absolute() and Path(value).is_absolute():
            if Path(value).parts[-len(rel.parts) :] == rel.parts:
                env = replace_at(env, path, named[path])
    return env
