"""The source -> engine -> sinks pipeline that ``vpengine run``/``predict`` drive, for any door to reuse:

- :mod:`vpengine.pipeline.run`: :class:`~vpengine.pipeline.run.Pipeline` (start, run, summary), ``run_pipeline``,
  and opening the sources of a run;
- :mod:`vpengine.pipeline.pacing`: lockstep and realtime feeding, one feed per camera, Ctrl-C;
- :mod:`vpengine.pipeline.summary`: what a run counts and the summary it makes.

Recent input frames (for pictures, overlays and output headers) are kept in :mod:`vpengine.recent_frames`, below
both this package and ros2/, which share it.
"""
