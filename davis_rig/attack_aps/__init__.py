"""The texture attack against a detector trained on real images, on APS frames: the real-data control."""
