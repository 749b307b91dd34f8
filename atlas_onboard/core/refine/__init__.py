"""Live refinement of the world map from the swarm's observations: evidence per marker,
its robust mean and covariance, and when a marker's refined pose may replace the world file's.

Evidence comes one image at a time: the world markers one camera saw in one image, each with its own
pose in the camera (the square's own solve, ``T_sensor_marker``) and that pose's 6x6 covariance. For
each marker seen with at least ``min_others`` other world markers, the others place the camera
(``T_world_sensor = T_world_other T_sensor_other^-1``, fused by information), and the camera places the
marker (``T_world_marker = T_world_sensor T_sensor_marker``): leave-one-out, a marker never confirms
itself. An image whose others do not agree with each other (a moved marker among them, a flipped
square) gives no evidence (counted). The evidence of a marker is accumulated over many images, and
its robust mean (outliers gated by Mahalanobis distance against the evidence's own scatter) is the
refined pose, with a covariance that counts views, not frames (successive frames from one place share
their errors).

A refined pose replaces the map's (:meth:`MapRefiner.step`) only when it is converged and
significant: enough independent views (images at least ``view_gap_s`` apart per camera), seen over a
spread of directions, a small sigma, and an offset from the current pose beyond its noise and beyond
``min_offset_m`` / ``min_offset_deg``. Each update moves one marker, the most significant, at most
``max_step_m`` and ``max_step_deg``, and drops the evidence it gave the others (gathered again against
its new pose). Anchors (surveyed markers) are never moved.

Conventions as in :mod:`atlas_onboard.core.covariance`: a pose's error is ``[dp, dtheta]``, ``dp`` in the
parent frame (m) and ``dtheta`` about the child's own axes (rad). Pure: the time is each image's
capture stamp (microseconds), passed in.

The package: :mod:`.records` (what goes in and comes out), :mod:`.placement` (where the other markers
of one image place the camera, leave-one-out), :mod:`.mean` (the robust mean of a marker's evidence),
:mod:`.refiner` (the evidence per marker, and when the map moves).
"""

from atlas_onboard.core.refine.mean import residuals
from atlas_onboard.core.refine.records import Estimate, Evidence, RefineOptions, Sighting, Update, WorldMarkerPose
from atlas_onboard.core.refine.refiner import MapRefiner

__all__ = ["Estimate", "Evidence", "MapRefiner", "RefineOptions", "Sighting", "Update", "WorldMarkerPose", "residuals"]
