// Blends the viewer's overlay (people, cursors, panel; drawn on the CPU at the window's
// resolution, straight alpha) over the presented scene: one full-screen triangle, each
// fragment reading its own overlay pixel. Blending is the pipeline's (src-alpha over).

@group(0) @binding(0) var overlay: texture_2d<f32>;

@vertex
fn vs_main(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    let x = f32(i32(i & 1u) * 4 - 1);
    let y = f32(i32(i >> 1u) * 4 - 1);
    return vec4<f32>(x, y, 0.0, 1.0);
}

@fragment
fn fs_main(@builtin(position) position: vec4<f32>) -> @location(0) vec4<f32> {
    let size = vec2<i32>(textureDimensions(overlay));
    let at = min(vec2<i32>(position.xy), size - vec2<i32>(1, 1));
    return textureLoad(overlay, at, 0);
}
