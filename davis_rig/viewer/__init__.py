"""Look at what the camera and the detector see: the session viewer (``davis-view``) and the live view of
``davis-record --view``, served as a local web page.

- :mod:`~davis_rig.viewer.render`: pure drawing kernels (event and APS images, boxes, crop outline, panels);
- :mod:`~davis_rig.viewer.recording`: a session on ``davis-eval``'s window grid, one displayed frame per window;
- :mod:`~davis_rig.viewer.detections`: RVT boxes scored on the fly or loaded from a ``davis-eval`` report;
- :mod:`~davis_rig.viewer.misses`: the windows and sequences the detector missed (the attack's successes);
- :mod:`~davis_rig.viewer.export`: the view as MP4 / GIF;
- :mod:`~davis_rig.viewer.server`, :mod:`~davis_rig.viewer.sessions_app`: the local web server and its API;
- :mod:`~davis_rig.viewer.live`: the live view beside a running recording.

Nothing is imported here: ``davis-record --help`` and ``davis-view --help`` stay fast.
"""
