"""Evaluation: a policy (or the baseline) run in the env on seeded episodes, and what is written
of them: rows, summaries, failures, figures, videos, diagnoses. Imports ``rl.env`` and
``rl.policy``, no room above them.

Modules:
    episodes:      seeded evaluation episodes (in this process or worker processes), rows,
                   traces, the summary.
    batched:       the same episodes on the batched simulator, all at once.
    failures:      how an episode fails (wedged, landed off), named and counted.
    episode_media: an episode's onboard frames as a video and a contact sheet.
    report:        ``rl eval``'s output folder: summary, rows, figures, stress tables.
    episode_video: ``rl episode``: one episode filmed from the camera and from outside.
    diagnose:      what each reward term pays under a controller.
    trajectories:  the PID baseline's poses, to render for the error model's memory.
"""
