"""The UNet's inference graph as ONNX (opset 17), built node by node from its weights (train.py's
layout) with the onnx package: the contract in train.py's docstring, batch norm folded into the
convolution before it, the soft-argmax as Softmax and a MatMul against the constant pixel grid,
presence as ReduceMean and Gemm. Nodes are named by layer (/enc1/enc1.0/Conv, /heat/Conv, ...),
which quantize.py uses to keep the keypoint head in float.
"""
import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

INPUT = 96
OPSET = 17
BN_EPS = 1e-5


def folded(arrays, block, conv, bn):
    """Conv weight and bias of `block.conv` followed by batch norm `block.bn` (running
    statistics), as one convolution."""
    scale = arrays[f"{block}.{bn}.weight"] / np.sqrt(arrays[f"{block}.{bn}.running_var"] + BN_EPS)
    weight = arrays[f"{block}.{conv}.weight"] * scale[:, None, None, None]
    bias = arrays[f"{block}.{bn}.bias"] - arrays[f"{block}.{bn}.running_mean"] * scale
    return weight.astype(np.float32), bias.astype(np.float32)


def export(arrays, path):
    """Writes the graph of the UNet whose weights (numpy arrays by name) are `arrays`."""
    levels = 1 + sum(1 for key in arrays if key.startswith("enc") and key.endswith(".0.weight"))
    nodes, initializers = [], []
    counts = {}

    def constant(name, value):
        initializers.append(numpy_helper.from_array(np.asarray(value), name))
        return name

    def node(op, scope, inputs, output=None, **attributes):
        """A node named /scope/Op (or /Op_k for repeats); its output's name unless given."""
        base = f"/{scope}/{op}" if scope else f"/{op}"
        k = counts.get(base, 0)
        counts[base] = k + 1
        name = base if k == 0 else f"{base}_{k}"
        out = output or f"{name}_output_0"
        nodes.append(helper.make_node(op, inputs, [out], name=name, **attributes))
        return out

    def conv(x, scope, layer, weight, bias, output=None):
        k = weight.shape[2]
        return node("Conv", scope, [x, constant(f"{layer}.weight", weight), constant(f"{layer}.bias", bias)], output,
                    kernel_shape=[k, k], pads=[k // 2] * 4, strides=[1, 1], dilations=[1, 1], group=1)

    def block(x, name):
        for conv_index, bn_index, relu_index in ((0, 1, 2), (3, 4, 5)):
            weight, bias = folded(arrays, name, conv_index, bn_index)
            x = conv(x, f"{name}/{name}.{conv_index}", f"{name}.{conv_index}", weight, bias)
            x = node("Relu", f"{name}/{name}.{relu_index}", [x])
        return x

    def max_pool(x):
        return node("MaxPool", None, [x], kernel_shape=[2, 2], strides=[2, 2], pads=[0, 0, 0, 0])

    x = "image"
    skips = []
    for k in range(1, levels):
        x = block(x if k == 1 else max_pool(x), f"enc{k}")
        skips.append(x)
    bottom = block(max_pool(x), "bottom")
    d = bottom
    for k in range(levels - 1, 0, -1):
        up = node("ConvTranspose", f"up{k}", [d, constant(f"up{k}.weight", arrays[f"up{k}.weight"]),
                                              constant(f"up{k}.bias", arrays[f"up{k}.bias"])],
                  kernel_shape=[2, 2], strides=[2, 2], pads=[0, 0, 0, 0])
        d = block(node("Concat", None, [up, skips[k - 1]], axis=1), f"dec{k}")
    conv(d, "seg", "seg", arrays["seg.weight"], arrays["seg.bias"], output="seg")
    heat = conv(d, "heat", "heat", arrays["heat.weight"], arrays["heat.bias"])
    # Soft-argmax: the expected (x, y) of each heatmap's softmax over the pixels.
    flat = node("Reshape", None, [heat, constant("heat_shape", np.array([0, 3, INPUT * INPUT], np.int64))])
    prob = node("Softmax", None, [flat], axis=2)
    ys, xs = np.meshgrid(np.arange(INPUT, dtype=np.float32), np.arange(INPUT, dtype=np.float32), indexing="ij")
    node("MatMul", None, [prob, constant("pixel_xy", np.stack([xs.ravel(), ys.ravel()], axis=1))], output="keypoints")
    pooled = node("ReduceMean", None, [bottom], axes=[2, 3], keepdims=0)
    node("Gemm", "presence", [pooled, constant("presence.weight", arrays["presence.weight"]),
                              constant("presence.bias", arrays["presence.bias"])], output="presence", transB=1)

    def port(name, shape):
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)

    graph = helper.make_graph(
        nodes, "unet_roi96", [port("image", [1, 3, INPUT, INPUT])],
        [port("seg", [1, 2, INPUT, INPUT]), port("keypoints", [1, 3, 2]), port("presence", [1, 1])],
        initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="millinav train.py")
    # IR version 8 (ONNX 1.10): what the committed model has, read by every onnxruntime since 1.10.
    model.ir_version = 8
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, path)
