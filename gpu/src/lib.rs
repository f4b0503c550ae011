//! GPU kernels through wgpu (WGSL compute; `common.wgsl` is every shader's prelude), each the twin of a CPU kernel in
//! `nephele-kernels` and tested against it (`tests.rs`): the same rays, the same march, the
//! same networks, results equal to within stated tolerances.
//!
//! * [`GpuContext`] opens the device a [`DeviceChoice`] asks for (`--device auto|cpu|gpu`):
//!   `auto` takes a hardware GPU when there is one and otherwise stays on the CPU; `gpu`
//!   also accepts a software Vulkan adapter (Mesa's lavapipe, what CI runs the tests on) and
//!   says so in its label.
//! * [`GpuInolfKernel`] is the i-NOLF kernel: the asset's tables uploaded once, one
//!   dispatch per batch, one invocation per pixel; behind [`RayKernel`] like every kernel.
//! * [`GpuNgpKernel`] is the i-NGP-style baseline (hash grid, two MLPs, occupancy
//!   skipping), so that GPU ratios between i-NOLF and its baseline compare like with like.
//! * [`GpuUNet`] is the stereo GI model's U-Net (issue 13), layer by layer: the farm's GI
//!   kernel runs its networks through it with `--device gpu` (the G-buffer stays on the
//!   CPU), and `nephele bench gi` measures it against the CPU forward.
//! * [`accelerate`] turns a loaded CPU kernel into its GPU twin where one exists.
//!
//! [`RayKernel`]: nephele_kernels::kernel::RayKernel

mod agreement;
mod context;
mod dispatch;
mod inolf;
mod ngp;
#[cfg(test)]
mod ngp_tests;
#[cfg(test)]
mod tests;
mod unet;
#[cfg(test)]
mod unet_tests;

use std::sync::Arc;

pub use agreement::{Agreement, DEPTH_RELATIVE_TOLERANCE};
pub use context::{DeviceChoice, GpuContext, GpuError};
pub use inolf::{GpuInolfKernel, MAX_SPECULAR_PARAMS};
pub use ngp::GpuNgpKernel;
pub use unet::GpuUNet;

/// The GPU as the kernels' registry sees it ([`Accelerator`]): i-NOLF assets and radiance
/// fields get their GPU twins, GI models their U-Nets; path-traced assets stay on the CPU.
///
/// [`Accelerator`]: nephele_kernels::assets::Accelerator
#[derive(Debug, Clone)]
pub struct GpuAccelerator(pub Arc<GpuContext>);

impl nephele_kernels::assets::Accelerator for GpuAccelerator {
    fn inolf(
        &self,
        kernel: &nephele_kernels::inolf::kernel::InolfKernel,
    ) -> Result<Arc<dyn nephele_kernels::kernel::RayKernel>, String> {
        let gpu = GpuInolfKernel::new(self.0.clone(), kernel).map_err(|e| e.to_string())?;
        tracing::info!(device = %self.0.label(), bytes = gpu.device_bytes(), "i-NOLF asset resident on the GPU");
        Ok(Arc::new(gpu))
    }

    fn ngp(
        &self,
        kernel: &nephele_kernels::ngp::NgpKernel,
    ) -> Result<Arc<dyn nephele_kernels::kernel::RayKernel>, String> {
        let gpu = GpuNgpKernel::new(self.0.clone(), kernel).map_err(|e| e.to_string())?;
        tracing::info!(device = %self.0.label(), bytes = gpu.device_bytes(), "radiance field resident on the GPU");
        Ok(Arc::new(gpu))
    }

    fn unet(&self, network: &nephele_nn::UNet) -> Result<Arc<dyn nephele_kernels::gi::UNetDevice>, String> {
        let gpu = GpuUNet::new(self.0.clone(), network).map_err(|e| e.to_string())?;
        Ok(Arc::new(gpu))
    }

    fn label(&self) -> String {
        self.0.label()
    }
}

/// Opens what `choice` asks for as the registry's accelerator: `None` means the CPU.
pub fn accelerator(choice: DeviceChoice) -> Result<Option<Arc<dyn nephele_kernels::assets::Accelerator>>, GpuError> {
    Ok(GpuContext::open(choice)?
        .map(|ctx| Arc::new(GpuAccelerator(ctx)) as Arc<dyn nephele_kernels::assets::Accelerator>))
}
