"""The loss and its assigner, one step, the run (detector then crop phase); it validates through prediction and evaluation."""
