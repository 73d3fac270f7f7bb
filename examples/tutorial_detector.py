"""The detector tutorial's own detector (docs/tutorials/detectors.md): the actor's last layer.

A trojan that sends the agent into lava must make one action win where a clean policy's would not,
and the layer that turns the embedding into action logits is the cheapest place to keep that
preference. The features: each action's weight-row norm and bias in that layer. Use it with
``rlbackdoors detect fit --plugin examples/tutorial_detector.py --detector last-layer ...``.
"""

from rlbackdoors.detect import FeatureDetector, register


@register
class LastLayer(FeatureDetector):
    name = "last-layer"
    description = "the actor's output layer: each action's weight-row norm and bias"

    def features(self, model):
        # model.weights: the state dict, read as data (TrojAI's layer names: actor.0, actor.2, ...)
        layers = [n for n in model.weights if n.startswith("actor.") and n.endswith(".weight")]
        last = max(layers, key=lambda n: int(n.split(".")[1]))
        weight, bias = model.weights[last], model.weights[last.removesuffix("weight") + "bias"]
        features = {}
        for action in range(weight.shape[0]):
            features[f"row_norm_{action}"] = float(weight[action].norm())
            features[f"bias_{action}"] = float(bias[action])
        return features
