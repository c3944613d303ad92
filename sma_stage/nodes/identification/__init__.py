"""The identification node's rooms: its parameters, the recording, the excitation, the refit and the
models in force, the watch's wiring. The node (sma_stage.nodes.identification_node) keeps the callbacks of
the recording and the health, and wires the rooms together."""
