"""Reading MCAP recordings back in tests (the mcap and mcap_ros2 readers)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def mcap_counts(path: Path) -> dict[str, int]:
    """Messages per channel topic, from the file's summary statistics."""
    with open(path, "rb") as handle:
        summary = make_reader(handle).get_summary()
    stats = summary.statistics.channel_message_counts
    return {channel.topic: stats.get(channel.id, 0) for channel in summary.channels.values()}


def ros_messages_in(path: Path, topic: str) -> list[Any]:
    """The decoded ROS 2 messages of one CDR topic, in log order (mcap_ros2's decoder)."""
    with open(path, "rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        return [decoded for *_, decoded in reader.iter_decoded_messages(topics=[topic])]
