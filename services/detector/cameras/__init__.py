"""Camera and recording sources beyond the folder and the live Azure Kinect (``sources.py``).

- :mod:`.realsense`: Intel RealSense D400-series cameras, and :mod:`.realsense_recording`:
  RealSense recordings (``.bag``, ``.db3``), through ``pyrealsense2`` (optional extra
  ``realsense``).
- :mod:`.kinect_recording`: Azure Kinect / Orbbec Femto recordings (``.mkv`` from
  ``k4arecorder``) through ``pyk4a`` (optional extra ``kinect``).
- :mod:`.convert`, :mod:`.lens` and :mod:`.clock`: what needs no SDK (colour formats, arrays to
  :class:`~services.detector.sources.CapturedFrame`, lens distortion, device times to host
  nanoseconds), so it is tested without a camera; :mod:`.handle`: closing an SDK handle that
  another thread reads from.

The SDKs are imported only when a source is opened; a missing SDK is a
:class:`~services.detector.sources.SourceUnavailable` whose message names the option and the
install command. See docs/cameras.md.
"""
