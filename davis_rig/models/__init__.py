"""Detectors used by the rig: ``davis_rig.models.rvt`` (RVT, recurrent event-camera detector)."""
