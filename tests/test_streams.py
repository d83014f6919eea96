"""The declared stream table: every row an output port of the contract with its message type, and
every viewer's conversions exactly the rows it shows."""

from __future__ import annotations

import pytest

from archery.protocol.keys import OUTPUT_PORTS, Keys
from archery.protocol.streams import STREAMS, VIEWERS, shown_by, stream


def test_every_row_is_an_output_port_of_its_message_type() -> None:
    kinds = {spec.pattern: spec for spec in OUTPUT_PORTS}
    for row in STREAMS:
        spec = kinds[row.port]
        assert spec.message == row.message.__name__, row.name
        assert row.follow == "events" or spec.kind == "pub", row.name  # an event is never skipped
        assert set(row.keys(Keys("lab"))) <= set(Keys("lab").output_streams())
        assert set(row.channels) <= set(VIEWERS), row.name


def test_the_rows_are_named_once_and_found_by_name() -> None:
    names = [row.name for row in STREAMS]
    assert len(names) == len(set(names))
    assert stream("joints").port == "{part}/state:o"
    with pytest.raises(KeyError, match="streams: joints"):
        stream("nonsense")
    with pytest.raises(KeyError, match="viewers"):
        shown_by("nonsense")


def test_the_ros2_node_converts_exactly_the_rows_it_shows_on_its_topics() -> None:
    from archery.apps.ros2.graph import CONVERSIONS, TOPICS

    rows = shown_by("ros2")
    assert set(CONVERSIONS) == {row.name for row in rows}
    feeds = {topic.name: topic.feed for topic in TOPICS}
    for row in rows:
        assert set(CONVERSIONS[row.name]) == set(row.channels["ros2"]), row.name
        assert {feeds[name] for name in row.channels["ros2"]} == {row.name}, row.name
    assert {feed for feed in feeds.values() if feed is not None} == set(CONVERSIONS)


def test_the_foxglove_bridge_converts_exactly_the_rows_it_shows_on_its_channels() -> None:
    from archery.apps.foxglove.channels import TOPICS
    from archery.apps.foxglove.feeds import CONVERSIONS

    rows = shown_by("foxglove")
    assert set(CONVERSIONS) == {row.name for row in rows}
    for row in rows:
        assert set(CONVERSIONS[row.name]) == set(row.channels["foxglove"]), row.name
        assert set(row.channels["foxglove"]) <= {topic.name for topic in TOPICS}, row.name


def test_the_yarp_bridge_converts_exactly_the_rows_yarp_shows() -> None:
    from archery.apps.yarp.bridge import CONVERSIONS

    assert set(CONVERSIONS) == {row.name for row in shown_by("yarp")}
    for row in shown_by("yarp"):  # a row followed latest-wins has no outbox; an event row has
        assert (CONVERSIONS[row.name].queued == 0) == (row.follow == "latest"), row.name
