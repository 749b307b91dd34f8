"""Why an observation or a peer's message was refused: the one vocabulary of every block.

Each reason is counted as ``rejected_<value>`` (by the node, in its status line, in STATUSTEXT and in
``docs/troubleshooting.md``); a link's counters carry the link's name in front (``peer0_rejected_bad_data``).
"""

from __future__ import annotations

from enum import StrEnum


class Rejection(StrEnum):
    """Why something received was dropped, grouped by the block that decides it."""

    # The MarkerData record itself (MarkerData.rejection, checked by the listener)
    NON_FINITE = "non_finite"
    ZERO_QUATERNION = "zero_quaternion"
    BAD_SIGMA = "bad_sigma"
    OUT_OF_RANGE = "out_of_range"
    BAD_QUALITY = "bad_quality"
    """A reprojection error that is negative or infinite, or an ambiguity ratio outside [0, 1]
    (NaN, unknown, is fine for both): a broken sender, whose record is not trusted."""
    BAD_COVARIANCE = "bad_covariance"
    """A detection covariance that is not 21 finite numbers making a positive definite 6x6 matrix
    (:meth:`MarkerData.rejection` checks the numbers and the variances, the listener the rest)."""
    INCONSISTENT_SIGMA = "inconsistent_sigma"
    """A ``sigma`` that contradicts the record's own covariance: the camera's position spread the
    covariance implies and ``sigma`` differ by more than ``SIGMA_COVARIANCE_TOLERANCE`` either way
    (:mod:`atlas_onboard.core.edge_covariance`). The detector computes both from the same corners; a
    record whose weight (sigma) and gate (covariance) disagree is not trusted with either."""

    # The listener: the world file and the planar ambiguity
    UNKNOWN_SENSOR = "unknown_sensor"
    """A sensor id the world file does not have (for a peer's observation decided before decoding)."""
    UNKNOWN_MARKER = "unknown_marker"
    OWN_MARKER = "own_marker"
    AMBIGUOUS = "ambiguous"
    """The two planar solutions fit almost equally well and the record carries no usable other one."""
    AMBIGUITY_UNRESOLVED = "ambiguity_unresolved"
    """Ambiguous with both solutions, but the current estimates could not say which is right (no
    estimate of the observer or the observed entity, or both solutions far from the prediction, or
    both about as close to it: see :mod:`atlas_onboard.core.ambiguity`)."""
    ATTITUDE_MISMATCH = "attitude_mismatch"
    """Neither of a single tag's two solutions implies the tilt the autopilot reports (see
    :mod:`atlas_onboard.core.attitude`): the detection, not gravity, is wrong."""

    # The graph's outlier gate (counted once per refused edge observation)
    OUTLIER = "outlier"
    TOO_FAST = "too_fast"
    """A candidate resting on peers' observations that would move its entity farther than its last
    estimate allows: that estimate's uncertainty plus the vehicle's top speed times the time since
    (:mod:`atlas_onboard.core.graph.gate`). Counted once per refused edge observation."""
    FUTURE_STAMP = "future_stamp"
    """A peer's capture stamp ahead of its arrival by more than that peer's measured clock offset and
    jitter allow (:mod:`atlas_onboard.core.peerclock`): it would make a pose look newer than the own
    camera's frames."""

    # The peer gate (mavlink/gate.py): origin binding before decoding, then duplicates and rates
    OWN_SENSOR = "own_sensor"
    """An observation by a sensor of this node's own entity: only our own cameras make those."""
    NOT_OWNER = "not_owner"
    """An observation by a sensor (or a fused pose of an entity) from a system id other than the node
    that the world file says runs the sensor's entity."""
    UNBOUND_SENSOR = "unbound_sensor"
    """An observation by a sensor of an entity that the world file's ``nodes`` section gives no node."""
    UNKNOWN_ORIGIN = "unknown_origin"
    """A fused pose from a system id that is no node of the world file."""
    BAD_STAMP = "bad_stamp"
    """A capture stamp more than ``MAX_SKEW_S`` from its arrival on our wall clock, refused before it
    is parked (a forged future stamp must not supersede the real observation)."""
    OWN_ECHO = "own_echo"
    """Our own observation coming back (a mesh or a router echoes broadcasts)."""
    DUPLICATE = "duplicate"
    RATE_LIMITED = "rate_limited"

    # The codec (mavlink/codec.py)
    BAD_VERSION = "bad_version"
    WRONG_FINGERPRINT = "wrong_fingerprint"
    """A peer with another world file."""
    MALFORMED = "malformed"
    TUNNEL_UNKNOWN_TYPE = "tunnel_unknown_type"
    TUNNEL_BAD_LENGTH = "tunnel_bad_length"

    # A link (mavlink/link.py): framing and signing
    BAD_DATA = "bad_data"
    BAD_SIGNATURE = "bad_signature"
    UNSIGNED_OR_BAD_SIGNATURE = "unsigned_or_bad_signature"
    """A protected message unsigned where signing is required, or signed and failing the check."""
    UNKNOWN_ID = "unknown_id"
    """A message id no public dialect of this pymavlink defines (never trusted: no CRC was checked)."""

    @property
    def counter(self) -> str:
        """The counter's name: ``rejected_<value>``."""
        return f"rejected_{self.value}"
