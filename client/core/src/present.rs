//! From the replica to the screen: keeping the GPU copy current, and putting the traced image and
//! the overlay on a target (a window's surface or a browser canvas).
//!
//! Why shared: the native window and the browser page differ only in where the target comes
//! from; the copy-then-trace-then-blit order, the nearest-neighbour enlargement of a frame
//! traced at reduced resolution and the overlay blend are the same code in both.

use brickcast_protocol::replica::Replica;

use crate::gpu::{GpuContext, GpuError, GpuScene, fullscreen_pipeline};
use crate::overlay::canvas::Canvas;
use crate::overlay::gpu::OverlayPass;

/// The WGSL of the blit pass.
pub const BLIT_WGSL: &str = include_str!("../../../shaders/blit.wgsl");

/// Colour a target is cleared to before anything is traced (the sky's horizon).
pub const CLEAR: wgpu::Color = wgpu::Color {
    r: 0.62,
    g: 0.74,
    b: 0.90,
    a: 1.0,
};

/// Brings `scene` up to date with `replica`: a new GPU copy when there is none, the scene's size
/// changed or the replica was reset (a resync), otherwise only what changed since the last call.
/// Returns whether anything was written.
pub fn sync_scene(
    ctx: &GpuContext,
    scene: &mut Option<GpuScene>,
    replica: &mut Replica,
) -> Result<bool, GpuError> {
    let size = replica.map.size();
    let stale = scene.as_ref().is_none_or(|s| s.size() != size);
    if replica.take_reset() || stale {
        let budget = replica.budget();
        *scene = Some(GpuScene::within(ctx, &mut replica.map, None, budget)?);
        return Ok(true);
    }
    match scene {
        Some(s) => Ok(s.update(ctx, &mut replica.map)?.writes > 0),
        None => Ok(false),
    }
}

/// The target to draw the next frame into, or `None` when there is nothing to draw on now
/// (minimised, covered, or a lost or outdated surface, which is configured again for the next
/// frame).
pub fn acquire(
    ctx: &GpuContext,
    surface: &wgpu::Surface<'_>,
    config: &wgpu::SurfaceConfiguration,
) -> Option<wgpu::SurfaceTexture> {
    match surface.get_current_texture() {
        wgpu::CurrentSurfaceTexture::Success(t) | wgpu::CurrentSurfaceTexture::Suboptimal(t) => {
            Some(t)
        }
        wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
            surface.configure(&ctx.device, config);
            None
        }
        _ => None,
    }
}

/// Draws a traced image (enlarged without blur) and the overlay onto a target.
pub struct Presenter {
    blit: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    pub overlay: OverlayPass,
}

impl Presenter {
    pub fn new(device: &wgpu::Device, format: wgpu::TextureFormat) -> Presenter {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("blit.wgsl"),
            source: wgpu::ShaderSource::Wgsl(BLIT_WGSL.into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("blit"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let blit = fullscreen_pipeline(device, "blit", &module, &layout, format, None);
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("nearest"),
            mag_filter: wgpu::FilterMode::Nearest,
            min_filter: wgpu::FilterMode::Nearest,
            ..Default::default()
        });
        Presenter {
            blit,
            layout,
            sampler,
            overlay: OverlayPass::new(device, format),
        }
    }

    /// Uploads the overlay's drawing when it changed.
    pub fn upload_overlay(&mut self, ctx: &GpuContext, canvas: &Canvas) {
        self.overlay.upload(&ctx.device, &ctx.queue, canvas);
    }

    /// Records: clear `target`, draw `image` over all of it (when there is one), blend the
    /// overlay on top.
    pub fn draw(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        image: Option<&wgpu::TextureView>,
    ) {
        let group = image.map(|view| {
            ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("blit"),
                layout: &self.layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: wgpu::BindingResource::TextureView(view),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: wgpu::BindingResource::Sampler(&self.sampler),
                    },
                ],
            })
        });
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("present"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(CLEAR),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let Some(group) = &group {
            pass.set_pipeline(&self.blit);
            pass.set_bind_group(0, group, &[]);
            pass.draw(0..3, 0..1);
        }
        self.overlay.draw(&mut pass);
    }
}
