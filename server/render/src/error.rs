//! [`RenderError`]: everything that can go wrong while rendering, each variant saying how to fix
//! it. Nothing in this crate panics on input.

/// An error of the renderer.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderError {
    /// No graphics adapter could be found for any enabled backend.
    #[error(
        "no graphics adapter found (tried: {tried}); on a machine without a GPU install Mesa's CPU \
         renderers (`apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri` for llvmpipe through \
         OpenGL, `apt-get install mesa-vulkan-drivers libvulkan1` for lavapipe through Vulkan) \
         and, if another Vulkan layer hides lavapipe, set NODEVICE_SELECT=1"
    )]
    NoAdapter {
        /// The backends that were tried.
        tried: String,
    },
    /// The adapter refused to create a device.
    #[error("the graphics adapter {adapter} refused to create a device: {reason}")]
    RequestDevice {
        /// Adapter name.
        adapter: String,
        /// wgpu's explanation.
        reason: String,
    },
    /// The device was lost (driver reset, GPU removed); create a new [`crate::Renderer`].
    #[error("the graphics device was lost ({reason}); create a new Renderer and upload the scenes again")]
    DeviceLost {
        /// Why, as the driver reported it.
        reason: String,
    },
    /// A view asked for a resolution the renderer cannot produce.
    #[error("resolution {resolution} is not supported: it must be between 1 and {max} pixels")]
    InvalidResolution {
        /// The resolution asked for.
        resolution: u32,
        /// The largest supported resolution.
        max: u32,
    },
    /// A view gave the wrong number of movable-object poses, or a pose that is not finite.
    #[error("view {view}: {reason}")]
    InvalidPoses {
        /// Index of the view in the batch.
        view: usize,
        /// What was wrong.
        reason: String,
    },
    /// A submitted batch was given to another renderer than the one that submitted it.
    #[error("the batch was submitted by another Renderer; finish it with that one")]
    ForeignBatch,
    /// A view's scene was uploaded by another renderer.
    #[error("view {view}: its scene was uploaded by another Renderer; upload it with this one")]
    ForeignScene {
        /// Index of the view in the batch.
        view: usize,
    },
    /// A scene has more movable objects than the renderer has pose slots.
    #[error("scene {scene} has {count} movable objects; the renderer draws at most {max}")]
    TooManyObjects {
        /// Scene id.
        scene: String,
        /// Its number of movable objects.
        count: usize,
        /// The most the renderer supports.
        max: usize,
    },
    /// An object's shape cannot be turned into triangles.
    #[error("object {object}: its shape cannot be triangulated: {reason}")]
    InvalidShape {
        /// The object's id.
        object: String,
        /// What was wrong.
        reason: String,
    },
    /// wgpu reported an error while rendering a batch (a bug in this crate or the driver).
    #[error("the graphics driver reported an error while rendering: {reason}")]
    Gpu {
        /// wgpu's message.
        reason: String,
    },
    /// Reading the rendered images back from the device failed.
    #[error("reading the rendered images back failed: {reason}")]
    Readback {
        /// What failed.
        reason: String,
    },
    /// Encoding a PNG failed.
    #[error("PNG encoding failed: {reason}")]
    Png {
        /// The encoder's message.
        reason: String,
    },
}
