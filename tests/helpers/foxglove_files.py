"""Reading a Foxglove MCAP file back (`--record-foxglove`): the mcap reader, and protobuf
messages decoded from the file's own schemas (FileDescriptorSets), as Foxglove does."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader


def foxglove_channels(path: Path) -> dict[str, tuple[str, str, str]]:
    """topic -> (message encoding, schema encoding, schema name) of every channel."""
    with open(path, "rb") as handle:
        summary = make_reader(handle).get_summary()
    return {
        c.topic: (
            c.message_encoding,
            summary.schemas[c.schema_id].encoding,
            summary.schemas[c.schema_id].name,
        )
        for c in summary.channels.values()
    }


def protobuf_messages_in(path: Path, topic: str) -> list[Any]:
    """The messages of one protobuf channel in log order, decoded with the classes built
    from the channel's schema (a FileDescriptorSet)."""
    with open(path, "rb") as handle:
        classes: dict[int, Any] = {}
        decoded = []
        for schema, _, message in make_reader(handle).iter_messages(topics=[topic]):
            if schema.id not in classes:
                classes[schema.id] = _message_class(schema.name, schema.data)
            decoded.append(classes[schema.id].FromString(message.data))
    return decoded


def _message_class(name: str, data: bytes) -> Any:
    files = list(descriptor_pb2.FileDescriptorSet.FromString(data).file)
    pool, added = descriptor_pool.DescriptorPool(), set()
    while files:  # each file after its dependencies
        ready = [f for f in files if set(f.dependency) <= added]
        if not ready:
            raise ValueError(f"{name}: unresolved dependencies")
        for file in ready:
            pool.Add(file)
            added.add(file.name)
            files.remove(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
