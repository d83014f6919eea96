"""The layout shipped with the bridge (`archery foxglove --layout FILE.json`): the robot in a 3D
panel, the camera's frame with the detector's marks, the distance per rollout and the world's
events; built with the Foxglove SDK's layout types, imported once in the Foxglove app."""

from __future__ import annotations

import foxglove.layouts as fl

from archery.apps.foxglove.channels import (
    CALIBRATION,
    EVENTS,
    IMAGE,
    MARKS,
    ROLLOUTS,
    SCENE,
    SERVICES,
)

__all__ = ["layout"]


def layout() -> fl.Layout:
    """The bridge's layout: 3D and camera side by side over the learning curve and the log."""
    three_d = fl.ThreeDeePanel(
        title="iCub",
        config=fl.ThreeDeeConfig(
            follow_tf="world",
            topics={SCENE.name: fl.BaseRendererSceneUpdateTopicSettings(visible=True)},
        ),
    )
    camera = fl.ImagePanel(
        title="target camera",
        config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(
                image_topic=IMAGE.name,
                calibration_topic=CALIBRATION.name,
                annotations={MARKS.name: fl.ImageAnnotationSettings(visible=True)},
            ),
        ),
    )
    curve = fl.PlotPanel(
        title="distance per rollout (m)",
        config=fl.PlotConfig(
            paths=[fl.PlotSeries(value=f"{ROLLOUTS.name}.distance", label="‖r‖ (m)")],
            x_axis_val="custom",
            x_axis_path=fl.PlotXAxisPath(value=f"{ROLLOUTS.name}.rollout"),
            x_axis_label="rollout",
            y_axis_label="m",
        ),
    )
    events = fl.LogPanel(title="world events", config=fl.LogConfig(topic_to_render=EVENTS.name))
    services = fl.RawMessagesPanel(
        title="services and rates", config=fl.RawMessagesConfig(topic_path=SERVICES.name)
    )
    top = fl.SplitContainer(
        direction="row",
        items=[
            fl.SplitItem(proportion=1, content=three_d),
            fl.SplitItem(proportion=1, content=camera),
        ],
    )
    bottom = fl.SplitContainer(
        direction="row",
        items=[
            fl.SplitItem(proportion=2, content=curve),
            fl.SplitItem(proportion=1, content=events),
            fl.SplitItem(proportion=1, content=services),
        ],
    )
    return fl.Layout(
        content=fl.SplitContainer(
            direction="column",
            items=[
                fl.SplitItem(proportion=2, content=top),
                fl.SplitItem(proportion=1, content=bottom),
            ],
        )
    )
