//! The compute pass that traces a frame (`shaders/trace.wgsl`) and reads it back.

use brickcast_protocol::render::MISS;
use brickcast_protocol::{Frame, Lighting, Projection};

use super::scene::{GpuScene, PAGES};
use super::{GpuContext, GpuError};

/// The tracer's WGSL source.
pub const TRACE_WGSL: &str = include_str!("../../../../shaders/trace.wgsl");

const WORKGROUP: u32 = 8;

/// The shader's `Frame` uniform, field for field.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct FrameUniform {
    eye: [f32; 4],
    forward: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    sun: [f32; 4],
    sky: [f32; 4],
    flags: [f32; 4],
    size: [u32; 4],
    region_dims: [u32; 4],
    cell_dims: [u32; 4],
    image: [u32; 4],
    occupied_lo: [i32; 4],
    occupied_hi: [i32; 4],
}

fn xyz0(v: [f32; 3], w: f32) -> [f32; 4] {
    [v[0], v[1], v[2], w]
}
fn uxyz(v: [u32; 3], w: u32) -> [u32; 4] {
    [v[0], v[1], v[2], w]
}

impl FrameUniform {
    fn new(scene: &GpuScene, p: &Projection, light: &Lighting) -> FrameUniform {
        let size = scene.size();
        // Every loop iteration crosses a plane, so nx+ny+nz (+ a few) bounds a ray; twice that
        // can only be reached by a bug, and then the ray ends as a miss instead of hanging.
        let budget = 2 * (size[0] + size[1] + size[2]) + 64;
        let lights = light.uniform();
        let occupied = scene
            .occupied_regions()
            .map(|(lo, hi)| (lo.map(|c| c as i32), hi.map(|c| c as i32)));
        FrameUniform {
            eye: xyz0(p.eye, 0.0),
            forward: xyz0(p.forward, 0.0),
            right: xyz0(p.right, 0.0),
            up: xyz0(p.up, 0.0),
            sun: lights.sun,
            sky: lights.sky,
            flags: lights.flags,
            size: uxyz(size, 0),
            region_dims: uxyz(scene.region_dims(), budget),
            cell_dims: uxyz(scene.cell_dims(), scene.page_shift()),
            image: [p.width, p.height, 0, 0],
            occupied_lo: occupied.map_or([0; 4], |(lo, _)| [lo[0], lo[1], lo[2], 1]),
            occupied_hi: occupied.map_or([0; 4], |(_, hi)| [hi[0], hi[1], hi[2], 1]),
        }
    }
}

/// The output of a frame: the image and what each pixel hit.
struct Target {
    width: u32,
    height: u32,
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    hits: wgpu::Texture,
    hits_view: wgpu::TextureView,
    generation: u64,
}

/// A frame read back from the GPU.
#[derive(Debug, Clone, PartialEq)]
pub struct GpuFrame {
    pub width: u32,
    pub height: u32,
    /// RGBA8, row-major, top row first.
    pub pixels: Vec<[u8; 4]>,
    /// Primary hit voxel per pixel.
    pub hits: Vec<Option<[u32; 3]>>,
}

impl GpuFrame {
    /// As the CPU renderer's [`Frame`], for comparing the two.
    pub fn to_frame(&self, size: [u32; 3]) -> Frame {
        Frame {
            width: self.width,
            height: self.height,
            pixels: self.pixels.clone(),
            hits: self
                .hits
                .iter()
                .map(|h| h.map_or(MISS, |v| brickcast_protocol::render::voxel_index(size, v)))
                .collect(),
        }
    }
}

/// The tracing pipeline and its output target.
pub struct Tracer {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
    target: Option<Target>,
    target_generation: u64,
    bind_group: Option<((u64, u64), wgpu::BindGroup)>,
}

fn storage_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only: true },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// Binding of the output image and of the per-pixel hits, after the uniform and scene buffers.
const IMAGE_BINDING: u32 = 3 + 3 * PAGES as u32;
const HITS_BINDING: u32 = IMAGE_BINDING + 1;

impl Tracer {
    pub fn new(ctx: &GpuContext) -> Result<Tracer, GpuError> {
        let device = &ctx.device;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("trace.wgsl"),
            source: wgpu::ShaderSource::Wgsl(TRACE_WGSL.into()),
        });
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }];
        entries.extend((1..IMAGE_BINDING).map(storage_entry));
        entries.push(wgpu::BindGroupLayoutEntry {
            binding: IMAGE_BINDING,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::StorageTexture {
                access: wgpu::StorageTextureAccess::WriteOnly,
                format: wgpu::TextureFormat::Rgba8Unorm,
                view_dimension: wgpu::TextureViewDimension::D2,
            },
            count: None,
        });
        entries.push(wgpu::BindGroupLayoutEntry {
            binding: HITS_BINDING,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::StorageTexture {
                access: wgpu::StorageTextureAccess::WriteOnly,
                format: wgpu::TextureFormat::Rg32Uint,
                view_dimension: wgpu::TextureViewDimension::D2,
            },
            count: None,
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("tracer"),
            entries: &entries,
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("tracer"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("tracer"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let uniform = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("frame"),
            size: std::mem::size_of::<FrameUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Tracer {
            layout,
            pipeline,
            uniform,
            target: None,
            target_generation: 0,
            bind_group: None,
        })
    }

    fn ensure_target(&mut self, ctx: &GpuContext, width: u32, height: u32) -> Result<(), GpuError> {
        if self
            .target
            .as_ref()
            .is_some_and(|t| t.width == width && t.height == height)
        {
            return Ok(());
        }
        let max = ctx.limits.max_texture_dimension_2d;
        if width > max || height > max {
            return Err(GpuError::Unsupported {
                adapter: ctx.adapter_name.clone(),
                what: format!("a {width}×{height} image (largest texture side is {max})"),
            });
        }
        let texture = target_texture(
            ctx,
            "traced image",
            (width, height),
            wgpu::TextureFormat::Rgba8Unorm,
            wgpu::TextureUsages::TEXTURE_BINDING,
        );
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let hits = target_texture(
            ctx,
            "hits",
            (width, height),
            wgpu::TextureFormat::Rg32Uint,
            wgpu::TextureUsages::empty(),
        );
        let hits_view = hits.create_view(&wgpu::TextureViewDescriptor::default());
        self.target_generation += 1;
        self.target = Some(Target {
            width,
            height,
            texture,
            view,
            hits,
            hits_view,
            generation: self.target_generation,
        });
        Ok(())
    }

    /// The traced image (after [`Tracer::encode`]), for presenting.
    pub fn image_view(&self) -> Option<&wgpu::TextureView> {
        self.target.as_ref().map(|t| &t.view)
    }

    /// Records a trace of `scene` into `encoder`.
    pub fn encode(
        &mut self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        scene: &GpuScene,
        projection: &Projection,
        lighting: &Lighting,
    ) -> Result<(), GpuError> {
        self.ensure_target(ctx, projection.width, projection.height)?;
        let Some(target) = &self.target else {
            return Ok(());
        };
        let uniform = FrameUniform::new(scene, projection, lighting);
        ctx.queue
            .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
        let key = (scene.generation(), target.generation);
        if self.bind_group.as_ref().is_none_or(|(k, _)| *k != key) {
            let buffers = scene.bindings();
            let mut entries = vec![wgpu::BindGroupEntry {
                binding: 0,
                resource: self.uniform.as_entire_binding(),
            }];
            entries.extend(
                buffers
                    .iter()
                    .enumerate()
                    .map(|(i, b)| wgpu::BindGroupEntry {
                        binding: 1 + i as u32,
                        resource: b.as_entire_binding(),
                    }),
            );
            entries.push(wgpu::BindGroupEntry {
                binding: IMAGE_BINDING,
                resource: wgpu::BindingResource::TextureView(&target.view),
            });
            entries.push(wgpu::BindGroupEntry {
                binding: HITS_BINDING,
                resource: wgpu::BindingResource::TextureView(&target.hits_view),
            });
            let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("tracer"),
                layout: &self.layout,
                entries: &entries,
            });
            self.bind_group = Some((key, group));
        }
        let Some((_, group)) = &self.bind_group else {
            return Ok(());
        };
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("trace"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, group, &[]);
        pass.dispatch_workgroups(
            projection.width.div_ceil(WORKGROUP),
            projection.height.div_ceil(WORKGROUP),
            1,
        );
        Ok(())
    }

    /// Traces one frame and waits for it.
    pub fn trace(
        &mut self,
        ctx: &GpuContext,
        scene: &GpuScene,
        projection: &Projection,
        lighting: &Lighting,
    ) -> Result<(), GpuError> {
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("trace"),
            });
        self.encode(ctx, &mut encoder, scene, projection, lighting)?;
        ctx.queue.submit([encoder.finish()]);
        ctx.wait()
    }

    /// Copies the last traced frame back to the CPU, waiting for it (native only).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn read_back(&self, ctx: &GpuContext) -> Result<GpuFrame, GpuError> {
        pollster::block_on(self.read_back_async(ctx))
    }

    /// Copies the last traced frame back to the CPU; in a browser the future resolves once the
    /// GPU is done, on native it has waited already.
    pub async fn read_back_async(&self, ctx: &GpuContext) -> Result<GpuFrame, GpuError> {
        self.start_read_back(ctx)?.finish(ctx).await
    }

    /// Records and submits the copies of the last traced frame; [`PendingFrame::finish`] reads
    /// them. Split so a caller that holds the tracer only briefly (a browser callback) can let
    /// go of it while the GPU works.
    pub fn start_read_back(&self, ctx: &GpuContext) -> Result<PendingFrame, GpuError> {
        let Some(target) = &self.target else {
            return Err(GpuError::NothingTraced);
        };
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("readback"),
            });
        let (image, image_row) = copy_out(ctx, &mut encoder, &target.texture, 4);
        let (hits, hits_row) = copy_out(ctx, &mut encoder, &target.hits, 8);
        ctx.queue.submit([encoder.finish()]);
        Ok(PendingFrame {
            width: target.width,
            height: target.height,
            image,
            image_row,
            hits,
            hits_row,
        })
    }
}

/// A frame on its way back from the GPU.
pub struct PendingFrame {
    width: u32,
    height: u32,
    image: wgpu::Buffer,
    image_row: u32,
    hits: wgpu::Buffer,
    hits_row: u32,
}

impl PendingFrame {
    pub async fn finish(self, ctx: &GpuContext) -> Result<GpuFrame, GpuError> {
        let (w, h) = (self.width, self.height);
        let image_bytes = map_read(ctx, &self.image).await?;
        let hit_bytes = map_read(ctx, &self.hits).await?;
        let mut pixels = Vec::with_capacity((w * h) as usize);
        let mut hits = Vec::with_capacity((w * h) as usize);
        let word = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        for y in 0..h as usize {
            let line = &image_bytes[y * self.image_row as usize..][..w as usize * 4];
            pixels.extend(line.chunks_exact(4).map(|p| [p[0], p[1], p[2], p[3]]));
            let line = &hit_bytes[y * self.hits_row as usize..][..w as usize * 8];
            hits.extend(line.chunks_exact(8).map(|p| {
                let (xy, z) = (word(&p[..4]), word(&p[4..]));
                (xy != MISS).then_some([xy & 0xFFFF, xy >> 16, z])
            }));
        }
        Ok(GpuFrame {
            width: w,
            height: h,
            pixels,
            hits,
        })
    }
}

/// A 2D texture the tracer writes (storage) and that can be read back (copy source), with
/// `usage` added.
fn target_texture(
    ctx: &GpuContext,
    label: &str,
    (width, height): (u32, u32),
    format: wgpu::TextureFormat,
    usage: wgpu::TextureUsages,
) -> wgpu::Texture {
    ctx.device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::STORAGE_BINDING | wgpu::TextureUsages::COPY_SRC | usage,
        view_formats: &[],
    })
}

/// Records a copy of `texture` (`texel_bytes` per texel) into a new mappable buffer; returns it
/// with its row pitch.
pub fn copy_out(
    ctx: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
    texel_bytes: u32,
) -> (wgpu::Buffer, u32) {
    let (w, h) = (texture.width(), texture.height());
    let row = (w * texel_bytes).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
        * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: u64::from(row) * u64::from(h),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(h),
            },
        },
        wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        },
    );
    (buffer, row)
}

/// Maps a `MAP_READ` buffer and copies its contents out.
pub async fn map_read(ctx: &GpuContext, buffer: &wgpu::Buffer) -> Result<Vec<u8>, GpuError> {
    let slice = buffer.slice(..);
    let (tx, rx) = futures_channel::oneshot::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    ctx.wait()?;
    match rx.await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => return Err(GpuError::Readback(e.to_string())),
        Err(_) => return Err(GpuError::Readback("map callback never ran".into())),
    }
    let bytes = slice
        .get_mapped_range()
        .map_err(|e| GpuError::Readback(e.to_string()))?
        .to_vec();
    buffer.unmap();
    Ok(bytes)
}
