"""ROS 2 interop: plug the engine into a ROS 2 graph and into rosbag2 recordings.

Three faces, one core:

* :mod:`vpengine.ros2.core` — everything that decides *what* goes on the wire and needs no middleware: image
  decoding (``sensor_msgs/Image``, ``CompressedImage``), the output topics of each head, the frame-id -> input-header
  book (every output carries its input's stamp and frame_id), rate-command parsing, ``/diagnostics`` content. Tested
  without DDS.
* :mod:`vpengine.ros2.bridge` — the core on CycloneDDS, speaking ROS 2's wire protocol (``rt/`` topic names,
  ``pkg::msg::dds_::Type_`` type names, XCDR1 little-endian CDR) so stock ROS 2 tools see a normal node's topics.
  No ROS 2 installation needed. ``vpengine ros2 --config ... --input-topic ...`` runs it.
* :mod:`vpengine.ros2.node` — the same core as an rclpy node, with services, for machines with ROS 2 installed.

Bags (rosbag2, sqlite3 and MCAP) go through :mod:`vpengine.io.bag`, which uses the same core. See ``docs/ros2.md``.
"""
