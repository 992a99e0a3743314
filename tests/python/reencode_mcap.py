"""Reads a ROS 2 MCAP recording with the independent mcap-ros2-support decoder, writes every
message again with its encoder, and prints what it read as JSON (the interop test compares it
with what the lab wrote, and replays the re-encoded file).

Usage: reencode_mcap.py IN.mcap OUT.mcap
"""

import json
import sys

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer


def main(src: str, dst: str) -> None:
    summary = {"topics": {}, "cloud": None, "odom_first": None, "tf_first": None}
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        writer = Writer(out)
        schemas = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_msgdef(schema.name, schema.data.decode())
            writer.write_message(
                topic=channel.topic,
                schema=schemas[schema.id],
                message=decoded,
                log_time=message.log_time,
                publish_time=message.publish_time,
                sequence=message.sequence,
            )
            topics = summary["topics"]
            topics[channel.topic] = topics.get(channel.topic, 0) + 1
            if schema.name == "sensor_msgs/msg/PointCloud2" and summary["cloud"] is None:
                stamp = decoded.header.stamp
                summary["cloud"] = {
                    "height": decoded.height,
                    "width": decoded.width,
                    "fields": [[p.name, p.offset, p.datatype] for p in decoded.fields],
                    "bytes": len(decoded.data),
                    "frame_id": decoded.header.frame_id,
                    "stamp_ns": stamp.sec * 1_000_000_000 + stamp.nanosec,
                }
            if schema.name == "nav_msgs/msg/Odometry" and summary["odom_first"] is None:
                p = decoded.pose.pose.position
                summary["odom_first"] = [p.x, p.y, p.z, decoded.child_frame_id]
            if channel.topic == "/tf" and summary["tf_first"] is None:
                t = decoded.transforms[0]
                summary["tf_first"] = [t.header.frame_id, t.child_frame_id, t.transform.rotation.w]
        writer.finish()
    print(json.dumps(summary))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
