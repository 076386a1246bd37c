"""The conventions every polrig module follows, written down in ``docs/conventions.md``.

Summary (the document is authoritative):

* Image arrays are ``[row, col]`` = ``[v, u]``; ``v`` grows down. Camera frame is OpenCV's
  (X right, Y down, Z forward).
* In-image polarization angles are measured from ``+u`` towards image up, i.e.
  counter-clockwise as displayed; AoLP in degrees in ``[0, 180)``.
* ``S1 = I0 - I90``, ``S2 = I45 - I135``; ideal analyzer ``I(t) = (S0 + S1 cos2t + S2 sin2t)/2``.
* Stokes bases follow Mitsuba 3: ``y = k x x`` with ``k`` the propagation direction.
  Emergent frame: ``x`` = camera X made perpendicular to the ray towards the camera.
  Incident frame: ``x`` = polarizer-stage zero axis made perpendicular to the ray from the light.
* Mueller arrays put matrix axes last; the linear block is ``M[..., :3, :3]``;
  colour Mueller images are ``(..., 3 colours, 3, 3)``.
"""

CONVENTIONS_VERSION = "1"
CONVENTIONS_DOC = "docs/conventions.md"

#: Colour channel names in the order polrig stores colour planes.
RGB = ("R", "G", "B")
#: Channel name of a mono sensor.
MONO = ("Y",)
