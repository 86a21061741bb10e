"""Independent evaluation scenes: a second scene generator, used ONLY to evaluate.

It checks how well the model transfers to a domain it was never trained on. It
shares no drawing, geometry, lamp or lighting code with :mod:`signal_light_node.synth`
(the training renderer) and imports nothing from it. All it shares with the project is
I/O and vocabulary: ``bagio``, ``conversions``, ``image_codec``, ``labels``, ``boxes``,
``results``, ``topics``, ``errors`` and the result message (``outputs.vehicle_lights``). Its bags use the topics, message types and
ground-truth rules of ``synth.bag``: JPEG ``/camera/image_raw/compressed``,
``/camera/tracked_objects`` (id = track ID) and ``/ground_truth/vehicle_lights`` (one
entry per detection, same order, probability 1 on the true states). So
``signal-light replay BAG -o OUT`` scores them like ``bags/day_street``.

How it differs from ``synth/``:

* Geometry and camera (``camera.py``): a real 3D world. The road runs along +Z. The
  camera is a pitched and rolled pinhole with barrel distortion, mounted on an ego car
  that moves and sways. Vehicles have world positions, headings and speeds: queues
  ahead that brake and hold gaps before a stop line, oncoming traffic that passes and
  turns from a front view into a side view, traffic crossing at an intersection,
  and a parked car with hazards (``traffic.py``). Views, sizes and occlusion all come
  from the projection.
* Vehicles (``models.py``, drawn by ``vehicle_drawing.py``): convex hexahedra (tyre
  slabs, body, tapered cabin or cargo box) in sedan, hatch, SUV, van and box-truck
  proportions. Faces are culled by their normals. Each face gets a gradient over a
  Lambert sun plus sky light, the glass reflects the sky, and some glass shows a sun
  glint.
* Lamps: lenses in vehicle face coordinates, set in a dark housing, with their own
  shapes and designs. Rear designs: ``euro_amber`` (L-shaped red clusters with separate
  amber blinkers), ``us_red`` (round red combined tail/brake/turn lamps), ``led_bar``
  (slanted blocks, a full-width tail bar and clear-lens amber strips) and ``vertical``
  (pillar strips). Front: headlights, amber blinkers, or DRL strips that switch to
  amber while blinking. Sides: wrap-around corner lamps and repeaters. Most cars also
  have a centre brake lamp on the rear glass.
* Lighting (``draw.py``, ``camera.py``, ``world.py``): everything renders into a LINEAR
  radiance buffer. Lenses are emissive and have a hot core. The sensor then applies
  exposure, colour crosstalk, a multi-scale bloom and an anamorphic glare streak,
  vignetting, lateral chromatic aberration, shot and read noise, light ISP denoising, an
  exponential tone curve and gamma. At night, saturated red lamps therefore turn
  pink-white at the core by themselves. A wet road gives stretched lamp reflections.
  Street lamps, lit windows and a red traffic signal act as distractors. Night exposure
  is about 4x the day's. In daylight a lit lens only adds about 1-2x the sunlit albedo,
  so lamps have less contrast, but a lit lens still clearly brightens.
* Signals: each vehicle blinks at 1.0-2.2 Hz with 30-70 % duty. A flash level is the
  lit share over the shutter time; bulbs react 60 ms slower than LEDs. Events are
  left and right turns (with a slight steer), hazards and braking episodes, and
  long quiet stretches fill the gaps. Tail lamps are always lit at night, and 30 %
  of vehicles also light them by day.
* Ground truth (``truth.py``): every object also goes into an id buffer. A lamp counts
  as seen when its face points at the camera (cos >= 0.15). Its unoccluded area, summed
  over the lamps of one function, must also reach 1/600 of the box's longer side squared
  (the rule of ``synth``). The brake counts only from rear-face lamps, so it is UNKNOWN
  from the front. In a side view, the far side's blinker is UNKNOWN. Blinkers are ON for
  the whole active period, and intent comes from ``intent_from_lights``. The view is the
  face toward the camera, in 90-degree sectors.
* Tracker (``tracker.py``): a box is the projected 3D box plus AR(1)-correlated jitter
  of 3 % in position and 4.5 % in size. Tracks are dropped when more than 70 % occluded, too
  small or mostly off the image, and 1.5 % of boxes drop at random. IDs are stable
  strings.

Usage: ``python -m signal_light_node.evalgen -o OUT --seed N --lighting day|night
[--frames 100] [--fps 10] [--width 1280 --height 720] [--vehicles N]
[--views all|behind] [--events mixed|none] [--jpeg-quality 80] [--preview sheet.png]``.

The committed bags were made with these exact commands. They use 640x360 so that
``bags/`` stays under the 15 MiB that ``test/test_committed_bags.py`` allows; 1280x720
night frames need about 120 KB each.

* ``bags/independent_day``: ``python -m signal_light_node.evalgen -o bags/independent_day
  --seed 13 --lighting day --width 640 --height 360 --frames 100 --jpeg-quality 80``
* ``bags/independent_night``: ``python -m signal_light_node.evalgen -o
  bags/independent_night --seed 23 --lighting night --width 640 --height 360 --frames 100
  --jpeg-quality 80``
* ``bags/night_tail_lamps``: ``python -m signal_light_node.evalgen -o bags/night_tail_lamps
  --seed 31 --lighting night --views behind --events none --vehicles 5 --width 640
  --height 360 --frames 100 --jpeg-quality 80``
"""

from signal_light_node.evalgen.bag import EvalBagSummary, write_eval_bag
from signal_light_node.evalgen.config import SceneConfig
from signal_light_node.evalgen.scene import EvalScene
from signal_light_node.evalgen.truth import EvalFrame, VehicleTruth

__all__ = ["EvalBagSummary", "write_eval_bag", "EvalFrame", "EvalScene", "SceneConfig",
           "VehicleTruth"]
