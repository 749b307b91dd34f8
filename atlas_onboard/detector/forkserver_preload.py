"""Imported by the worker processes' forkserver only (:mod:`atlas_onboard.detector.workers`), before it
forks any worker: it makes the AprilTag library detector the workers will use (its families from the
environment the node set), so that its decoding tables (35 MB for tag36h11) are made once and shared by
every worker, copy-on-write pages that are only ever read."""

from __future__ import annotations

import os

from atlas_onboard.detector.backends import shared_library

FAMILIES_ENV = "ATLAS_ONBOARD_WORKER_FAMILIES"

if os.environ.get(FAMILIES_ENV):
    shared_library(os.environ[FAMILIES_ENV], 1)
