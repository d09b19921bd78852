//! The GPU side of the client: device, the scene's buffers, and the tracing pass.

mod context;
pub mod scene;
pub mod tracer;

pub use context::{BackendChoice, GpuContext, TRACER_STORAGE_BUFFERS, new_instance};
pub use scene::{GpuScene, UploadStats};
pub use tracer::{GpuFrame, Tracer};

/// A pipeline that draws one full-screen triangle (`vs_main`, `fs_main` of `module`) into a
/// target of `format`: how the viewer presents the traced image and blends its overlay.
pub fn fullscreen_pipeline(
    device: &wgpu::Device,
    label: &str,
    module: &wgpu::ShaderModule,
    layout: &wgpu::BindGroupLayout,
    format: wgpu::TextureFormat,
    blend: Option<wgpu::BlendState>,
) -> wgpu::RenderPipeline {
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &[Some(layout)],
        immediate_size: 0,
    });
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout: Some(&pipeline_layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState::default(),
        depth_stencil: None,
        multisample: wgpu::MultisampleState::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some("fs_main"),
            compilation_options: Default::default(),
            targets: &[Some(wgpu::ColorTargetState {
                format,
                blend,
                write_mask: if blend.is_some() {
                    wgpu::ColorWrites::COLOR
                } else {
                    wgpu::ColorWrites::ALL
                },
            })],
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// Everything that can go wrong on the GPU side, naming the adapter where it matters.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no usable GPU adapter: {0} (is a Vulkan driver installed? try `apt-get install mesa-vulkan-drivers`)"
    )]
    NoAdapter(String),
    #[error("could not open a device on {adapter}: {reason}")]
    Device { adapter: String, reason: String },
    #[error("{adapter} does not support {what}")]
    Unsupported { adapter: String, what: String },
    #[error("the scene's {what} need {bytes} bytes but {adapter} allows at most {max} for them")]
    TooBig {
        adapter: String,
        what: &'static str,
        bytes: u64,
        max: u64,
    },
    #[error("the GPU copy holds a {expected:?} scene, not {got:?}")]
    SceneMismatch { expected: [u32; 3], got: [u32; 3] },
    #[error("nothing has been traced yet")]
    NothingTraced,
    #[error("reading the frame back failed: {0}")]
    Readback(String),
}

#[cfg(test)]
mod tests {
    /// Every WGSL file in `shaders/` parses and validates with naga, independent of any device.
    #[test]
    fn shaders_validate_with_naga() {
        use wgpu::naga;
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shaders");
        let mut checked = 0;
        for entry in std::fs::read_dir(dir).expect("shaders/ exists") {
            let path = entry.expect("readable dir").path();
            if path.extension().is_none_or(|e| e != "wgsl") {
                continue;
            }
            let source = std::fs::read_to_string(&path).expect("readable shader");
            let module = naga::front::wgsl::parse_str(&source)
                .unwrap_or_else(|e| panic!("{}: {}", path.display(), e.emit_to_string(&source)));
            naga::valid::Validator::new(
                naga::valid::ValidationFlags::all(),
                naga::valid::Capabilities::empty(),
            )
            .validate(&module)
            .unwrap_or_else(|e| panic!("{}: {}", path.display(), e.emit_to_string(&source)));
            checked += 1;
        }
        assert!(
            checked >= 2,
            "expected trace.wgsl and blit.wgsl, found {checked}"
        );
    }
}
