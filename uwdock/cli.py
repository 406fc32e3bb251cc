"""``uwdock``: one command over every command group (``uwdock perception eval`` is
``perception eval``), and the console scripts of the six groups. A group's module is imported
only when one of its commands is called, so ``<group> --help`` is quick and the footage commands
run without the simulator or the learning stack installed."""

from __future__ import annotations

from uwdock.dockcore import early_signals

early_signals.hold()  # first: a signal landing while click loads is held, not fatal

import importlib  # noqa: E402

import click  # noqa: E402

from uwdock.dockcore.cli import CONTEXT, run_group  # noqa: E402

#: command group -> the extra that installs what its commands need (None: the base install)
EXTRAS: dict[str, str | None] = {
    "markers": None,
    "perception": None,
    "calibration": None,
    "datasets": "sim",
    "sim": "sim",
    "rl": "rl",
    "rl.deploy": "vehicle",
}


#: ``fit-water``'s summary: the command is ``datasets``' (it crosses the sim -> perception seam)
#: and ``sim`` lends it (:data:`LENT`), so ``sim fit-water`` is the same command.
FIT_WATER = (
    "Fit the underwater model's attenuation, backscatter and veiling light per channel to "
    "frames of a known target (a chessboard or the DS marker board) seen at several ranges; "
    "writes a water file that every --water option takes."
)

#: group -> {command: the package whose ``cli`` module defines it}: commands a group shows as
#: its own although another module defines them (the architecture keeps ``sim`` below
#: ``perception``; the umbrella, above both, joins them). The vehicle's commands live in
#: ``rl.deploy``, which loads neither torch nor SAPIEN (``uwdock[vehicle]``).
LENT: dict[str, dict[str, str]] = {
    "sim": {"fit-water": "datasets", "vehicle": "rl.deploy"},
    "rl": {"node": "rl.deploy", "replay": "rl.deploy"},
}

#: command group -> (its help text, {command: the first paragraph of its help}): what
#: ``<group> --help`` shows without importing the group's module (``uwdock.<group>.cli``, which
#: imports everything its commands use). ``tests/test_uwdock_cli.py`` checks it word for word
#: against the groups themselves.
COMMANDS: dict[str, tuple[str, dict[str, str]]] = {
    "markers": (
        "3D Binary Markers: printable parts, flat sheets, the marker set file.",
        {
            "dictionaries": "List the marker dictionaries OpenCV offers, with bits and marker "
            "count.",
            "generate": "Write STL parts (white insert, black enclosure), render meshes, "
            "previews, a true-scale PDF/SVG sheet and the marker set file for the given IDs.",
        },
    ),
    "perception": (
        "Perception: 3DBM detection and docking-station pose from the marker board.",
        {
            "detect": "Detect markers in INPUT (an image, a folder of images, a video or a ROS "
            "bag's image topic) and solve the DS pose.",
            "eval": "Evaluate detection and DS pose on INPUT (images, a video, a ROS bag's image "
            "topic, or a labelled dataset folder).",
            "pipelines": "List the preprocessing pipelines.",
        },
    ),
    "calibration": (
        "Calibration: camera intrinsics and the camera-to-vehicle extrinsics.",
        {
            "export": "Write the intrinsics of CAMERA_FILE as ROS camera_info YAML or a Kalibr "
            "camchain.",
            "extrinsics": "Show or set T_body_cam (camera cv frame in body FRD) in a camera file.",
            "import": "Convert SOURCE, a ROS camera_info YAML or a Kalibr camchain, into a "
            "camera file.",
            "intrinsics": "Calibrate K and distortion from SOURCE: a folder of images, a video "
            "or a ROS bag of the target.",
            "reference-camera": "Write the reference Girona downward camera (968x732, 55 deg "
            "HFOV) with its T_body_cam.",
            "stereo": "Calibrate a stereo pair (T_right_left, rectification, epipolar error) "
            "from views of the target in LEFT and RIGHT, or in one ROS bag LEFT.",
        },
    ),
    "datasets": (
        "Datasets: labelled synthetic frames and loaders for real footage.",
        {
            "render": "Render images (+ labels.jsonl in the dataset format) for given or random "
            "poses: the ``synth`` engine fed with explicit vehicle poses (``--poses``) or a few "
            "random ones.",
            "fit-water": FIT_WATER,
            "synth": "Render a labelled dataset of the docking station from random AUV poses.",
            "tank-report": "Predict how far above the docking station your camera decodes 1 and "
            "3 of its markers in your water: renders the DS straight below the camera at each "
            "altitude and runs the detector (rendered, not guessed).",
        },
    ),
    "sim": (
        "Simulation: SAPIEN AUV and docking-station physics, underwater camera rendering.\n\n"
        "Rendered frames for given poses: `datasets render`; a docking episode video: "
        "`rl episode`.",
        {
            "fit-water": FIT_WATER,
            "vehicle": "Run the simulator as the vehicle on ROS 2 topics: the rendered downward "
            "camera, the drifting navigation, USBL fixes and /clock out; body wrench commands "
            "in (zero-order hold, its own timeout).",
            "water": "List the water presets, clearest first: attenuation and backscatter per "
            "channel (1/m), veiling light and forward-scatter blur.",
        },
    ),
    "rl": (
        "Reinforcement learning: docking env, PPO training, evaluation, export.",
        {
            "convert-policy": "Convert a policy folder of the pickled format (SB3's policy.zip, "
            "vecnormalize.pkl) into the data format every command loads (model.json + "
            "weights.npz; nothing in it can run code). The same actions, bit for bit.",
            "episode": "Run the scripted PID controller in the docking env and write a "
            "side-by-side MP4 of the downward camera (with water) and an outside view, plus "
            "summary.json.",
            "eval": "Evaluate a policy (or the PID baseline) over seeded episodes.",
            "export": "Export a policy to ONNX (observation normalisation included); the .json "
            "beside it carries the env the policy was trained in (one line names its settings), "
            "which `rl eval` and the deployment runner take by default.",
            "fit-error-model": "Fit the image-derived error model from a labelled dataset "
            "(`datasets synth`).",
            "node": "Run the docking node on ROS 2 topics (DDS, no ROS install needed).",
            "replay": "Run a recorded mission (ROS 1 .bag, ROS 2 folder, .db3 or .mcap) through "
            "the node's chain on message time: writes replay.mcap (inputs and outputs), "
            "summary.json and a plot.",
            "sweep": "Sweep whole training runs over seeds and config values with Ray Tune, each "
            "trial a run folder that resumes from its own checkpoints.",
            "train": "Train a docking policy (PPO with the paper's hyperparameters by default), "
            "or a whole recipe of stages (`--recipe shipped --seed N`).",
            "trajectories": "Record the PID baseline's docking trajectories as a pose CSV with "
            "sequence, step and time columns (`datasets render --poses` renders them): frames "
            "consecutive in time, for fitting the error model's memory.",
        },
    ),
}


def load_group(name: str) -> click.Group:
    """The command group ``name`` itself: ``uwdock.<name>.cli`` imported (a missing optional
    package is a usage error naming the extra that installs it)."""
    extra = EXTRAS[name]
    try:
        module = importlib.import_module(f"uwdock.{name}.cli")
    except ModuleNotFoundError as exc:
        if exc.name and not exc.name.startswith("uwdock"):
            hint = f"pip install 'uwdock[{extra}]'" if extra else "reinstall uwdock"
            raise click.UsageError(
                f"'{name}' needs the Python package {exc.name!r}, not installed here ({hint})"
            ) from None
        raise
    return module.cli


class LazyGroup(click.Group):
    """Command group ``name`` as its console script and ``uwdock <name>`` see it: its help and
    command list come from :data:`COMMANDS`; its module (with the libraries its commands use:
    OpenCV, SAPIEN, torch ...) is imported only when a command is called, so ``<name> --help``
    and a mistyped command cost no more than click (click's documented lazy-loading pattern)."""

    def __init__(self, name: str) -> None:
        help_text = COMMANDS[name][0]
        super().__init__(
            name=name,
            help=help_text,
            short_help=" ".join(help_text.split("\n\n")[0].split()),  # uwdock's listing
            context_settings=CONTEXT,
        )

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS[self.name][1])

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS[self.name][1]:
            return None
        owner = LENT.get(self.name, {}).get(cmd_name, self.name)
        return load_group(owner).get_command(ctx, cmd_name)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The listing click writes for the loaded group (same truncation), from the table."""
        names = self.list_commands(ctx)
        limit = formatter.width - 6 - max(len(n) for n in names)
        summaries = COMMANDS[self.name][1]
        rows = [(n, click.Command(n, help=summaries[n]).get_short_help_str(limit)) for n in names]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


_LAZY = {name: LazyGroup(name) for name in COMMANDS}


class _LazyGroups(click.Group):
    """``uwdock``: the six lazy groups, listed with the first line of their own help."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        return _LAZY.get(name)


@click.group(cls=_LazyGroups, context_settings=CONTEXT)
@click.version_option(package_name="uwdock", prog_name="uwdock")
def cli() -> None:
    """Vision-in-the-loop underwater docking.

    Each group is also its own command: `uwdock rl eval` is `rl eval`.
    """


def main() -> None:
    """``uwdock``."""
    run_group(cli)


def _console_script(name: str):
    """The entry point of the console script ``name`` (``[project.scripts]``)."""

    def script() -> None:
        run_group(_LAZY[name])

    script.__doc__ = f"``{name}``."
    return script


# the console scripts of the six groups (``markers``, ``perception`` ...)
markers = _console_script("markers")
perception = _console_script("perception")
calibration = _console_script("calibration")
datasets = _console_script("datasets")
sim = _console_script("sim")
rl = _console_script("rl")


if __name__ == "__main__":  # pragma: no cover
    main()
