"""Marker maps from flights: the recording format, bundle adjustment, and the record and map commands."""
