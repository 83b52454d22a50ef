"""The device step of an update as a few fused stages: the rows in view gathered and activated
(``select_rows``), the supervision loss with its gradient (``fused_loss``), and the chain rule, regulariser, Adam
and position noise on the map's rows (``step_rows``). :mod:`.device_reference` and
:mod:`.device_reference_loss` are the plain-torch forms (any device, no host sync); ``triton_*`` the same stages
as Triton kernels (CUDA, or Triton's interpreter on CPU tensors)."""
