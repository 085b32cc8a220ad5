"""Reading a result MCAP back as a viewer would: with the `mcap` library, every channel's
schema checked to be a `foxglove.*` one, messages decoded with the protobuf descriptors the
file carries (the SDK's own schemas)."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def read_result(path: Path) -> dict[str, list]:
    """Decoded messages per topic, after checking every channel's schema."""
    messages: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None, f"{path} has no summary section"
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert schema.name.startswith("foxglove."), (channel.topic, schema.name)
            assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
        for _schema, channel, _message, decoded in reader.iter_decoded_messages():
            messages.setdefault(channel.topic, []).append(decoded)
    return messages


def schema_names(path: Path) -> dict[str, str]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}


def cloud_array(msg):
    """A decoded foxglove.PointCloud as a dict of float32 columns by field name."""
    import numpy as np

    data = np.frombuffer(msg.data, dtype="<f4").reshape(-1, msg.point_stride // 4)
    return {f.name: data[:, f.offset // 4] for f in msg.fields}


def decode(schema_name: str, descriptor_set: bytes, payload: bytes):
    """One protobuf message of `schema_name` from the FileDescriptorSet a channel carries."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    files = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))
    return cls.FromString(payload)


def cloud_in_frame(msg):
    """A decoded foxglove.PointCloud's x, y, z (N, 3) in its frame: under the cloud's pose."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    cols = cloud_array(msg)
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    q, p = msg.pose.orientation, msg.pose.position
    return Rotation.from_quat([q.x, q.y, q.z, q.w]).apply(xyz) + np.array([p.x, p.y, p.z])
