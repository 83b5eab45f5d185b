#!/usr/bin/env python3
"""Writes a tiny ONNX model whose input shape differs from the pipeline's (for a start-up test)."""
import sys

import onnx
from onnx import TensorProto, helper

inp = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 64, 64])
out = helper.make_tensor_value_info("seg", TensorProto.FLOAT, [1, 3, 64, 64])
graph = helper.make_graph([helper.make_node("Identity", ["image"], ["seg"])], "wrong_shape", [inp], [out])
model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
model.ir_version = 8
onnx.save(model, sys.argv[1])
