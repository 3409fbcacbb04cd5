"""USB layer: the only package importing pyusb.

- :mod:`davis_rig.usb.transport` — discovery, open/claim, version gates, vendor requests, bulk reads;
- :mod:`davis_rig.usb.virtual` — ``VirtualDavis346Backend``, a real ``usb.backend.IBackend`` with a DAVIS346 model
  (``device``: the model, ``backend``: the pyusb side, ``transfers``: libusb's asynchronous transfers);
- :mod:`davis_rig.usb.sources` — data sources (transfer list, replay, encoded scene) and ``Faults``;
- :mod:`davis_rig.usb.replay` — the replay file format (reader/writer).
"""
