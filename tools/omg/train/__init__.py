"""OMG training (PyTorch, CPU). See tools/omg/README.md."""
