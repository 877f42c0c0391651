"""Which measurement model consumes which event type.

The localizers look every measurement event up here: its model validates it, and builds the
likelihoods (and the Gaussian-sum filter's linear rows) of a batch of them. A new sensor's model
is one class (:mod:`relloc.filter.measurement`) registered here, by its sensor descriptor's
registration (:func:`relloc.sensors.register`) or by a :func:`register` call of its own; neither
filter nor any localizer changes. Models are built and fused in registration order.
"""

from __future__ import annotations

from relloc.filter.measurement import MeasurementModel
from relloc.filter.ranges import RangeBatch
from relloc.filter.sightings import SightingBatch
from relloc.filter.vectors import RelativePositionBatch

MODELS: dict[type, type[MeasurementModel]] = {}
"""Event type -> the model class that consumes it, in registration order."""


def register(model: type[MeasurementModel]) -> None:
    """Make ``model`` the consumer of each of its ``events`` types."""
    for event_type in model.events:
        MODELS[event_type] = model


def unregister(model: type[MeasurementModel]) -> None:
    """Remove ``model``'s event types (a plug-in that is switched off again)."""
    for event_type in model.events:
        if MODELS.get(event_type) is model:
            del MODELS[event_type]


def model_for(event: object) -> type[MeasurementModel] | None:
    """The model class of ``event``'s type, or ``None`` if no model consumes it."""
    return MODELS.get(type(event))


register(RangeBatch)
register(RelativePositionBatch)
register(SightingBatch)
