"""Optimisation: the photometric/depth losses (:mod:`.losses`), the map's Adam (:mod:`.adam`, its kernel
:mod:`.adam_kernels`) and the compiled CPU update, D-SSIM and fused-loss kernels (:mod:`.update_kernels`,
:mod:`.dssim_kernels`, :mod:`.loss_kernels`).

``from eligsir_o3d.optim import LossConfig`` (the path of the first release, when this package was one module) keeps
working: the losses' names resolve lazily, so importing a kernel module does not import the losses."""

_LOSSES = ("LossConfig", "dssim", "dssim_torch", "supervision_loss")


def __getattr__(name: str):
    if name in _LOSSES:
        from . import losses

        return getattr(losses, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
