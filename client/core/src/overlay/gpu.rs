//! The overlay on the GPU: a texture the size of the window, rewritten only when the CPU drawing
//! changed, and a pass that blends it over the frame (`shaders/overlay.wgsl`).

use super::canvas::Canvas;

pub struct OverlayPass {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    texture: Option<(wgpu::Texture, wgpu::BindGroup, u32, u32)>,
    /// Hash of the pixels last uploaded: unchanged frames upload nothing.
    uploaded: u64,
}

impl OverlayPass {
    pub fn new(device: &wgpu::Device, format: wgpu::TextureFormat) -> OverlayPass {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("overlay.wgsl"),
            source: wgpu::ShaderSource::Wgsl(
                include_str!("../../../../shaders/overlay.wgsl").into(),
            ),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("overlay"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Float { filterable: false },
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: false,
                },
                count: None,
            }],
        });
        let pipeline = crate::gpu::fullscreen_pipeline(
            device,
            "overlay",
            &module,
            &layout,
            format,
            Some(wgpu::BlendState::ALPHA_BLENDING),
        );
        OverlayPass {
            pipeline,
            layout,
            texture: None,
            uploaded: 0,
        }
    }

    /// Uploads `canvas` if it differs from what the texture holds.
    pub fn upload(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, canvas: &Canvas) {
        let (w, h) = (canvas.width.max(1), canvas.height.max(1));
        if canvas.width == 0 || canvas.height == 0 {
            return;
        }
        let resized = self
            .texture
            .as_ref()
            .is_none_or(|(_, _, tw, th)| (*tw, *th) != (w, h));
        if resized {
            let texture = device.create_texture(&wgpu::TextureDescriptor {
                label: Some("overlay"),
                size: wgpu::Extent3d {
                    width: w,
                    height: h,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            });
            let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("overlay"),
                layout: &self.layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&view),
                }],
            });
            self.texture = Some((texture, group, w, h));
            self.uploaded = 0;
        }
        let hash = hash_pixels(canvas);
        if hash == self.uploaded {
            return;
        }
        if let Some((texture, _, _, _)) = &self.texture {
            queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                bytemuck::cast_slice(&canvas.pixels),
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * w),
                    rows_per_image: Some(h),
                },
                wgpu::Extent3d {
                    width: w,
                    height: h,
                    depth_or_array_layers: 1,
                },
            );
            self.uploaded = hash;
        }
    }

    /// Blends the overlay over what `pass` has drawn.
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        if let Some((_, group, _, _)) = &self.texture {
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, group, &[]);
            pass.draw(0..3, 0..1);
        }
    }
}

/// FNV-1a over the pixels (a few MB a frame: cheap next to uploading them again).
fn hash_pixels(canvas: &Canvas) -> u64 {
    let bytes: &[u8] = bytemuck::cast_slice(&canvas.pixels);
    let mut h: u64 =
        0xcbf2_9ce4_8422_2325 ^ u64::from(canvas.width) << 32 ^ u64::from(canvas.height);
    for chunk in bytes.chunks_exact(8) {
        h ^= u64::from_le_bytes(chunk.try_into().unwrap_or([0; 8]));
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h | 1
}
