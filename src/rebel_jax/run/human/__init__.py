"""A person in the loop: the labelling page, its label file and the clips it shows.

``--teacher human`` serves a page (:mod:`~rebel_jax.run.human.server`) where a person answers each
feedback session's queries between jitted rounds; the answers go to ``RUN_DIR/labels.jsonl``
(:mod:`~rebel_jax.run.human.labels`) and into ``Trainer.session_learn`` as data
(:mod:`~rebel_jax.run.human.session`). ``--teacher replay`` re-runs those answers from the file.
"""

from rebel_jax.run.human.clips import ClipError
from rebel_jax.run.human.labels import LabelError
from rebel_jax.run.human.server import is_loopback
from rebel_jax.run.human.session import HostTeacher, HumanOptions, redact_token

HOST_TEACHERS = ("human", "replay")
"""Teachers whose sessions the host runs between rounds."""

HumanError = (ClipError, LabelError)
"""What a human or replay run stops on, with a message for the person."""

__all__ = [
    "HOST_TEACHERS",
    "ClipError",
    "HostTeacher",
    "HumanError",
    "HumanOptions",
    "LabelError",
    "is_loopback",
    "redact_token",
]
