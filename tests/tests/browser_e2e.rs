//! The browser viewer in a real browser (chromium, software WebGPU) against a real server on
//! loopback: the page's traced frame against the CPU renderer, edits both ways between the page
//! and a native client, the messages a user gets when something is wrong, and a server restart.

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use brickcast_client::link::Link;
use brickcast_protocol::render::{MISS, colour_distance, render, voxel_index};
use brickcast_protocol::wire::{ClientMsg, EditOp, ServerMsg, View};
use brickcast_protocol::{Camera, Colour, Lighting};
use brickcast_tests::browser::Browser;
use brickcast_tests::{TEST_SCENE, TestServer, fetch, http_get, wait_until};

fn local() -> SocketAddr {
    "127.0.0.1:0".parse().expect("address")
}

/// Same rule as the native twin test: colours within 2 steps where the voxel agrees, and a
/// handful of edge pixels where float rounding on another GPU tips a ray past a voxel corner.
const COLOUR_TOLERANCE: u32 = 2;

fn viewer_url(server: &TestServer, scene: &str) -> String {
    format!("http://{}/scenes/{scene}", server.addr)
}

/// Sends one edit from a native client and waits for its ack.
fn native_edit(server: &TestServer, ops: Vec<EditOp>) -> Result<u64> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let url = format!("ws://{}/scenes/demo/ws", server.addr);
        let mut link = Link::connect(&url, "native", 0, None, None).await?;
        link.send(&ClientMsg::Edit { client_seq: 1, ops }).await?;
        loop {
            match tokio::time::timeout(Duration::from_secs(20), link.next()).await?? {
                Some(ServerMsg::Ack {
                    seq: Some(seq),
                    applied,
                    ..
                }) if applied > 0 => {
                    link.close().await;
                    return Ok(seq);
                }
                Some(ServerMsg::Ack { rejected, .. }) => bail!("edit rejected: {rejected:?}"),
                Some(_) => continue,
                None => bail!("the server closed the connection"),
            }
        }
    })
}

/// The page's exact-size frame of the scene equals the CPU renderer's: same voxel (or miss) at
/// every pixel, colours within tolerance; and the first picture and the sync were timed.
#[test]
fn page_frame_matches_the_cpu_renderer() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let server = TestServer::start(dir.path(), local())?;
    let mut browser = Browser::start(320, 180)?;
    browser.goto(&viewer_url(&server, "demo"))?;
    let state = browser.wait_state(
        "s.synced_ms !== null && s.first_picture_ms !== null",
        60_000,
    )?;
    println!("page state after sync: {state}");
    assert!(state["first_picture_ms"].as_f64().is_some(), "{state}");
    assert!(
        state["adapter"]
            .as_str()
            .is_some_and(|a| a.contains("WebGpu")),
        "the page traces through WebGPU: {state}"
    );

    // The page keeps colours as `--colours bounded` does: the reference is such a copy, so
    // the page's decoding of bounded-error blocks is checked too.
    let exact = fetch(&server.url("demo"))?.map;
    let mut map = brickcast_protocol::BrickMap::new(exact.size())?;
    map.set_colour_bound(brickcast_protocol::blocks::Quality::default().bound());
    map.write_bricks(
        exact
            .bricks()
            .map(|(b, _)| (b.cell, Some((b.mask, b.colours)))),
    )?;
    map.rebuild_clearance();
    let mix = brickcast_protocol::palette::Mix::of(&map);
    assert!(
        mix.blocks[0] + mix.blocks[1] > 0,
        "the demo has bricks in blocks: {mix:?}"
    );
    let size = map.size();
    let cameras = [
        Camera::overview(size),
        Camera {
            eye: [-20.0, 40.0, 64.0],
            target: [64.0, 10.0, 64.0],
            fov_y: 70.0,
        },
    ];
    for camera in cameras {
        let (w, h) = (96, 54);
        let frame = browser.trace(w, h, camera.eye, camera.target, camera.fov_y)?;
        let (pixels, hits) = (frame.pixels, frame.hits);
        let cpu = render(
            &map,
            &camera.project(w, h).context("camera")?,
            &Lighting::default(),
            0,
        );
        let mut hit_mismatches = Vec::new();
        let mut colour_mismatches = Vec::new();
        let mut hit_pixels = 0;
        for i in 0..(w * h) as usize {
            let page_hit = hits[i].map_or(MISS, |v| voxel_index(size, v));
            if cpu.hits[i] != MISS {
                hit_pixels += 1;
            }
            if page_hit != cpu.hits[i] {
                hit_mismatches.push((i as u32 % w, i as u32 / w, cpu.hits[i], page_hit));
            } else if colour_distance(cpu.pixels[i], pixels[i]) > COLOUR_TOLERANCE {
                colour_mismatches.push((i as u32 % w, i as u32 / w, cpu.pixels[i], pixels[i]));
            }
        }
        let allowance = 3 + (w * h) as usize / 2000;
        assert!(
            hit_pixels > 500,
            "the camera {camera:?} sees the scene ({hit_pixels} hits)"
        );
        assert!(
            hit_mismatches.len() <= allowance,
            "{} of {} pixels hit another voxel in the page than on the CPU (first: {:?})",
            hit_mismatches.len(),
            w * h,
            &hit_mismatches[..hit_mismatches.len().min(5)]
        );
        assert!(
            colour_mismatches.is_empty(),
            "colours differ by more than {COLOUR_TOLERANCE} at {} pixels (first: {:?})",
            colour_mismatches.len(),
            &colour_mismatches[..colour_mismatches.len().min(5)]
        );
    }

    // The scene list names the scene and its thumbnail is a PNG of the scene.
    let list = http_get(server.addr, "/")?;
    assert!(list.contains("href=\"/scenes/demo\""), "{list}");
    assert!(list.contains(&format!(
        "{}×{}×{}",
        TEST_SCENE[0], TEST_SCENE[1], TEST_SCENE[2]
    )));
    let thumb = browser.eval(&format!(
        "fetch('http://{}/scenes/demo/thumb.png').then(r => r.blob()).then(b => createImageBitmap(b)).then(i => [i.width, i.height])",
        server.addr
    ))?;
    assert_eq!(thumb, serde_json::json!([320, 180]));
    server.stop()
}

/// `?budget=` on a world larger than the budget: the page holds the working set the server
/// streams (level 0 around the camera, coarse bricks further away), within the budget in its
/// copy and on the GPU, and traces it as the CPU traces the same working set built from the
/// whole scene. Without `?budget=` (256 MiB) the small scene is held whole.
#[test]
fn the_page_holds_a_working_set_within_its_budget() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let server = TestServer::start_with(dir.path(), local(), |c| c.demo_size = [512, 64, 512])?;
    let mut browser = Browser::start(320, 180)?;
    let budget = 200 * 1024;
    browser.goto(&format!("{}?budget=200KiB", viewer_url(&server, "demo")))?;
    let state = browser.wait_state(
        "s.synced && s.working_set !== null && s.gpu_bytes !== null && s.frames > 0",
        120_000,
    )?;
    println!("page state with a budget: {state}");
    assert_eq!(state["budget"], budget, "{state}");
    assert!(state["stand_ins"].as_u64().unwrap_or(0) > 0, "{state}");
    for what in ["scene_bytes", "gpu_bytes"] {
        let bytes = state[what].as_u64().context("bytes")?;
        assert!(bytes <= budget, "{what}: {bytes} of {budget}: {state}");
    }
    let exact = fetch(&server.url("demo"))?.map;
    assert!(state["bricks"].as_u64().unwrap_or(0) < exact.brick_count());
    let ws = &state["working_set"];
    let coord = |v: &serde_json::Value| -> Result<[u32; 3]> {
        let a: Vec<u32> = serde_json::from_value(v.clone())?;
        a.try_into()
            .map_err(|_| anyhow::anyhow!("three numbers: {v}"))
    };
    let rule = brickcast_protocol::working_set::Rule {
        eye: coord(&ws["eye"])?,
        near: ws["near"].as_u64().context("near")? as u32,
        top: ws["top"].as_u64().context("top")? as u32,
    };
    let pyramid = brickcast_protocol::lod::Pyramid::build(&exact)?;
    let mut held = brickcast_protocol::working_set::build(&exact, &pyramid, &rule)?;
    held.rebuild_clearance();
    // From the working set's eye region looking across it, and from above the whole world.
    let eye = rule.eye.map(|r| (r * 32 + 16) as f32);
    let size = held.size();
    let cameras = [
        Camera {
            eye: [eye[0], 60.0, eye[2]],
            target: [eye[0] + 200.0, 10.0, eye[2] + 120.0],
            fov_y: 70.0,
        },
        Camera::overview(size),
    ];
    for camera in cameras {
        let (w, h) = (96, 54);
        let frame = browser.trace(w, h, camera.eye, camera.target, camera.fov_y)?;
        let cpu = render(
            &held,
            &camera.project(w, h).context("camera")?,
            &Lighting::default(),
            0,
        );
        let mut mismatches = 0;
        let mut hit_pixels = 0;
        for i in 0..(w * h) as usize {
            let page_hit = frame.hits[i].map_or(MISS, |v| voxel_index(size, v));
            hit_pixels += usize::from(cpu.hits[i] != MISS);
            mismatches += usize::from(page_hit != cpu.hits[i]);
        }
        assert!(
            hit_pixels > 500,
            "{camera:?} sees the world ({hit_pixels} hits)"
        );
        assert!(
            mismatches <= 3 + (w * h) as usize / 2000,
            "{mismatches} of {} pixels hit another voxel in the page than on the CPU from {camera:?}",
            w * h
        );
    }

    browser.goto(&viewer_url(&server, "demo"))?;
    let state = browser.wait_state("s.synced && s.frames > 0", 120_000)?;
    assert_eq!(state["budget"], 256u64 << 20, "{state}");
    assert!(state["working_set"].is_null(), "held whole: {state}");
    assert_eq!(state["bricks"].as_u64(), Some(exact.brick_count()));
    server.stop()
}

/// An edit made with the mouse in the page reaches a native client, and a native edit shows
/// in the page's next frame.
#[test]
fn edits_cross_between_the_page_and_a_native_client() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let server = TestServer::start(dir.path(), local())?;
    let mut browser = Browser::start(320, 180)?;
    browser.goto(&viewer_url(&server, "demo"))?;
    browser.wait_state(
        "s.synced_ms !== null && s.first_picture_ms !== null",
        60_000,
    )?;

    // Look straight down at the middle of the scene and place a voxel with a right click at
    // the centre of the canvas.
    let before = fetch(&server.url("demo"))?.map;
    let (cx, cz) = (
        TEST_SCENE[0] as f32 / 2.0 + 0.5,
        TEST_SCENE[2] as f32 / 2.0 + 0.5,
    );
    browser.eval(&format!(
        "window.brickcast.set_camera(new Float32Array([{cx}, 60.5, {cz}]), new Float32Array([{cx}, 0, {}]))",
        cz + 0.01
    ))?;
    // The click turns into a ray through the last traced frame: wait for one from there.
    browser.wait_state("s.frames > 3", 10_000)?;
    let frames = browser.state()?.context("state")?["frames"]
        .as_u64()
        .unwrap_or(0);
    browser.wait_state(&format!("s.frames > {}", frames + 2), 10_000)?;
    browser.click(160.0, 90.0, "right")?;
    let mut after = before.clone();
    let placed = wait_until(Duration::from_secs(20), || {
        after = fetch(&server.url("demo"))
            .map(|r| r.map)
            .unwrap_or_else(|_| before.clone());
        after.solid_voxels() == before.solid_voxels() + 1
    });
    assert!(
        placed,
        "the page's right click placed one voxel ({} → {})",
        before.solid_voxels(),
        after.solid_voxels()
    );

    // Ctrl+Z in the page takes it back (the page's own undo history).
    browser.call(serde_json::json!({"op": "key", "key": "Control+z"}))?;
    let undone = wait_until(Duration::from_secs(20), || {
        fetch(&server.url("demo")).is_ok_and(|r| r.map.solid_voxels() == before.solid_voxels())
    });
    assert!(undone, "Ctrl+Z in the page undid its voxel");

    // The box tool: X, then a right-button drag across the middle of the canvas fills a box
    // of more than one voxel on the ground (resolved by the server); Ctrl+Z takes it back.
    browser.call(serde_json::json!({"op": "key", "key": "x"}))?;
    browser.wait("window.brickcast.tool() === 'box'", 5_000)?;
    browser.drag([120.0, 90.0], [200.0, 100.0], "right")?;
    let mut boxed = 0;
    let drew = wait_until(Duration::from_secs(20), || {
        boxed = fetch(&server.url("demo"))
            .map(|r| r.map.solid_voxels())
            .unwrap_or(0);
        boxed > before.solid_voxels() + 1
    });
    assert!(
        drew,
        "the page's box drag filled a box ({} → {boxed})",
        before.solid_voxels()
    );
    browser.call(serde_json::json!({"op": "key", "key": "Control+z"}))?;
    let undone = wait_until(Duration::from_secs(20), || {
        fetch(&server.url("demo")).is_ok_and(|r| r.map.solid_voxels() == before.solid_voxels())
    });
    assert!(undone, "Ctrl+Z took the box back as one step");

    // Alt+click takes the colour under the pointer into the colour well (the page's copy may
    // round colours by up to 12/255: `?colours=exact` is not set).
    let hit = browser
        .trace(9, 9, [cx, 60.5, cz], [cx, 0.0, cz + 0.01], 60.0)?
        .hits[4 * 9 + 4]
        .context("the centre pixel hits the ground")?;
    let want = before
        .get(hit)
        .context("the ground under the centre")?
        .to_rgb8();
    browser.click_with(160.0, 90.0, "left", &["Alt"])?;
    let well = browser.wait(
        "document.getElementById('colour').value !== '#d93b3b' && document.getElementById('colour').value",
        5_000,
    )?;
    let well = well.as_str().unwrap_or_default().to_string();
    let got = brickcast_protocol::Colour::parse_hex(&well)
        .with_context(|| format!("the well holds {well:?}"))?
        .to_rgb8();
    assert!(
        (0..3).all(|i| got[i].abs_diff(want[i]) <= 16),
        "picked {well} for {want:?}"
    );

    // The scene's shared palette: the page lists it; a swatch a native client sets shows
    // there, its number key draws with it, and Shift+click on another swatch sets that one
    // for everyone (the server's copy holds it).
    browser.wait(
        "document.querySelectorAll('#swatches button').length === 32 && !document.getElementById('tools').hidden",
        10_000,
    )?;
    let teal = Colour::from_rgb8(0, 128, 128);
    native_edit(
        &server,
        vec![EditOp::Swatch {
            index: 4,
            colour: teal,
        }],
    )?;
    browser.wait_state(&format!("s.swatches[4] === '{}'", teal.to_hex()), 20_000)?;
    browser.call(serde_json::json!({"op": "key", "key": "5"}))?;
    browser.wait(
        &format!(
            "document.getElementById('colour').value === '{}'",
            teal.to_hex()
        ),
        5_000,
    )?;
    let at = browser.eval(
        "(() => { const r = document.querySelector('#swatches [data-swatch=\"6\"]').getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2]; })()",
    )?;
    let (x, y) = (
        at[0].as_f64().context("swatch x")?,
        at[1].as_f64().context("swatch y")?,
    );
    browser.click_with(x, y, "left", &["Shift"])?;
    let shared = wait_until(Duration::from_secs(20), || {
        fetch(&server.url("demo")).is_ok_and(|r| r.map.swatches().get(6) == teal)
    });
    assert!(shared, "Shift+click on swatch 7 set it for everyone");

    // The select tool: V, then a drag selects a box of voxels (nothing is edited); a native
    // client sees it in the page's presence.
    browser.call(serde_json::json!({"op": "key", "key": "v"}))?;
    browser.wait("window.brickcast.tool() === 'select'", 5_000)?;
    let voxels_before_select = fetch(&server.url("demo"))?.map.solid_voxels();
    browser.drag([120.0, 90.0], [200.0, 100.0], "left")?;
    let state = browser.wait_state("s.selection !== null", 10_000)?;
    let selected = state["selection"].clone();
    assert!(selected.is_array(), "{selected}");
    assert_eq!(
        fetch(&server.url("demo"))?.map.solid_voxels(),
        voxels_before_select,
        "selecting edits nothing"
    );
    // Ctrl+C copies it on the server, Ctrl+V pastes it onto the face under the pointer (more
    // voxels), Ctrl+Z takes the paste back.
    browser.call(serde_json::json!({"op": "key", "key": "Control+c"}))?;
    browser.call(serde_json::json!({"op": "key", "key": "Control+v"}))?;
    let mut now = 0;
    let pasted = wait_until(Duration::from_secs(20), || {
        now = fetch(&server.url("demo"))
            .map(|r| r.map.solid_voxels())
            .unwrap_or(0);
        now > voxels_before_select
    });
    assert!(
        pasted,
        "Ctrl+V pasted nothing ({voxels_before_select} → {now})"
    );
    browser.call(serde_json::json!({"op": "key", "key": "Control+z"}))?;
    let unpasted = wait_until(Duration::from_secs(20), || {
        fetch(&server.url("demo")).is_ok_and(|r| r.map.solid_voxels() == voxels_before_select)
    });
    assert!(unpasted, "Ctrl+Z took the paste back");

    // A native user present with a view shows in the page's roster, and F follows its camera.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let url = format!("ws://{}/scenes/demo/ws", server.addr);
    let mut native = runtime.block_on(Link::connect(&url, "native", 0, None, None))?;
    let eye = [10.5, 50.5, 20.5];
    runtime.block_on(native.send(&ClientMsg::Presence {
        view: Some(View {
            eye,
            forward: [1.0, -0.2, 0.0],
        }),
        cursor: None,
        selection: None,
    }))?;
    browser.wait_state("s.others.includes('native')", 20_000)?;
    let page_selection = runtime.block_on(async {
        loop {
            match tokio::time::timeout(Duration::from_secs(20), native.next()).await {
                Ok(Ok(Some(ServerMsg::Presence { states, .. }))) => {
                    if let Some(s) = states.iter().find_map(|s| s.selection) {
                        return Some(s);
                    }
                }
                Ok(Ok(Some(_))) => continue,
                _ => return None,
            }
        }
    });
    let page_selection = page_selection.context("the native client saw the page's selection")?;
    assert_eq!(
        serde_json::json!([page_selection.min, page_selection.max]),
        selected
    );
    browser.call(serde_json::json!({"op": "key", "key": "f"}))?;
    let followed = browser.wait_state(
        &format!(
            "s.camera && Math.abs(s.camera[0] - {}) < 0.01 && Math.abs(s.camera[1] - {}) < 0.01 && Math.abs(s.camera[2] - {}) < 0.01",
            eye[0], eye[1], eye[2]
        ),
        20_000,
    );
    assert!(
        followed.is_ok(),
        "F in the page rides along with the native user's camera"
    );
    runtime.block_on(native.close());

    // A native client puts a red voxel in the page's view, right under the camera.
    let pos = [cx as u32, 50, cz as u32];
    let red = Colour::from_rgb8(255, 0, 0);
    native_edit(&server, vec![EditOp::Set { pos, colour: red }])?;
    let mut seen = None;
    let shown = wait_until(Duration::from_secs(20), || {
        let frame = browser.trace(9, 9, [cx, 60.5, cz], [cx, 0.0, cz + 0.01], 60.0);
        seen = frame.ok().map(|f| f.hits[4 * 9 + 4]);
        seen == Some(Some(pos))
    });
    assert!(
        shown,
        "the page's centre pixel hits the natively placed voxel {pos:?}: {seen:?}"
    );
    // The history panel lists the paste (newest first); with nothing selected (a right click
    // of the select tool clears it), its restore puts the whole scene back as it was after
    // the paste (the pasted voxels again, the red voxel gone), as one undo step.
    browser.call(serde_json::json!({"op": "key", "key": "v"}))?;
    browser.click_with(200.0, 100.0, "right", &[])?;
    browser.wait_state("s.selection === null", 10_000)?;
    let before_restore = fetch(&server.url("demo"))?.map.solid_voxels();
    browser.eval("document.getElementById('history-button').click()")?;
    browser.wait(
        "[...document.querySelectorAll('#changes li')].some(li => li.textContent.includes(' paste by '))",
        20_000,
    )?;
    let view = browser.eval(
        "[...document.querySelectorAll('#changes li')].find(li => li.textContent.includes(' paste by ')).querySelector('a').getAttribute('href')",
    )?;
    assert!(
        view.as_str()
            .is_some_and(|h| h.starts_with("/scenes/demo~")),
        "{view}"
    );
    browser.eval(
        "[...document.querySelectorAll('#changes li')].find(li => li.textContent.includes(' paste by ')).querySelector('button').click()",
    )?;
    let restored = wait_until(Duration::from_secs(20), || {
        fetch(&server.url("demo")).is_ok_and(|r| r.map.solid_voxels() == now)
    });
    assert!(
        restored,
        "the restore put the pasted voxels back ({now} wanted)"
    );
    browser.call(serde_json::json!({"op": "key", "key": "Control+z"}))?;
    let unrestored = wait_until(Duration::from_secs(20), || {
        fetch(&server.url("demo")).is_ok_and(|r| r.map.solid_voxels() == before_restore)
    });
    assert!(unrestored, "Ctrl+Z took the restore back");
    // The paste's view link opens the scene as it was then: read-only, and the page says so.
    let view = view.as_str().context("the view link")?.to_string();
    let past = view.trim_start_matches("/scenes/");
    browser.goto(&viewer_url(&server, past))?;
    let state = browser.wait_state("s.synced && s.frames > 0", 60_000)?;
    assert_eq!(state["role"], serde_json::json!("Viewer"), "{state}");
    let note = browser.eval("document.getElementById('note').textContent")?;
    assert!(
        note.as_str()
            .is_some_and(|n| n.contains("as it was at sequence")),
        "{note}"
    );
    server.stop()
}

/// A bad token, an unknown scene and a browser without WebGPU each tell the user what is wrong.
#[test]
fn the_page_explains_what_is_wrong() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let server = TestServer::start_with(dir.path(), local(), |c| {
        c.auth = brickcast_server::auth::Auth::parse("ed-token editor alice\nv-token viewer bob\n")
            .expect("auth");
    })?;
    let mut browser = Browser::start(320, 180)?;
    let tools_shown =
        "(() => { const t = document.getElementById('tools'); return !!t && !t.hidden; })()";

    browser.goto(&format!("{}#token=wrong", viewer_url(&server, "demo")))?;
    let message = browser.wait(
        "(() => { const m = document.getElementById('message'); return !m.hidden && m.textContent; })()",
        30_000,
    )?;
    assert!(
        message
            .as_str()
            .is_some_and(|m| m.contains("needs an access token")),
        "{message}"
    );
    let form = browser.eval("!document.getElementById('token-form').hidden")?;
    assert_eq!(form, serde_json::json!(true), "the token form is offered");
    assert_eq!(
        browser.eval(tools_shown)?,
        serde_json::json!(false),
        "no editing tools over the message"
    );

    // The right token, typed into the form, makes an editor.
    browser.eval(
        "document.getElementById('token').value = 'ed-token'; document.getElementById('token-form').requestSubmit()",
    )?;
    let state = browser.wait_state("s.status === 'live'", 60_000)?;
    assert_eq!(state["role"], "Editor", "{state}");
    browser.wait(tools_shown, 10_000)?;
    // A lighting key says what it switched.
    browser.eval("window.brickcast.press('KeyO', false)")?;
    browser.wait(
        "document.getElementById('status').textContent.includes('ambient occlusion off')",
        10_000,
    )?;

    // A viewer's link: no editing tools, a note that fits the page when a click is ignored,
    // the resolution from `?scale=` and the bar's menu.
    let url = viewer_url(&server, "demo");
    browser.goto(&format!("{url}?scale=2#token=v-token"))?;
    let state = browser.wait_state("s.status === 'live'", 60_000)?;
    assert_eq!(state["role"], "Viewer", "{state}");
    let status = "document.getElementById('status').textContent";
    let line = browser.wait(
        &format!(
            "{status}.includes('1/2 resolution') && {status}.includes('watching') && {status}"
        ),
        10_000,
    )?;
    assert!(
        !line.as_str().is_some_and(|l| l.contains("brush")),
        "{line}"
    );
    assert_eq!(browser.eval("document.getElementById('scale').value")?, "2");
    assert_eq!(
        browser.eval(tools_shown)?,
        serde_json::json!(false),
        "a viewer has no tools"
    );
    browser.eval(
        "(() => { const p = document.getElementById('scale'); p.value = '4'; p.dispatchEvent(new Event('change')); })()",
    )?;
    browser.wait(&format!("{status}.includes('1/4 resolution')"), 10_000)?;
    browser.click(160.0, 90.0, "left")?;
    let note = browser.wait(
        "(() => { const n = document.getElementById('note'); const r = n.getBoundingClientRect(); return n.textContent && [r.left, r.right, r.top, window.innerWidth]; })()",
        10_000,
    )?;
    let [left, right, top, width] = [0, 1, 2, 3].map(|i| note[i].as_f64().unwrap_or(f64::NAN));
    assert!(
        left >= 0.0 && right <= width && top >= 0.0,
        "the whole note is on the page: {note}"
    );

    browser.goto(&viewer_url(&server, "nowhere"))?;
    let text = browser.eval("document.getElementById('message').textContent")?;
    assert!(
        text.as_str().is_some_and(|t| t.contains("no scene called")),
        "{text}"
    );
    assert_eq!(browser.eval(tools_shown)?, serde_json::json!(false));
    drop(browser);

    let mut plain = Browser::without_webgpu()?;
    plain.goto(&viewer_url(&server, "demo"))?;
    let failed = plain.wait("window.brickcastFailed", 10_000)?;
    assert_eq!(failed, "no-webgpu");
    let text = plain.eval("document.getElementById('message').textContent")?;
    assert!(
        text.as_str().is_some_and(|t| t.contains("no WebGPU")),
        "{text}"
    );
    // It stops there: no scene synced for nothing, no frame rate of nothing drawn.
    let state = plain.wait_state("s.status === 'failed'", 10_000)?;
    let received = state["bytes_in"].clone();
    std::thread::sleep(Duration::from_millis(1500));
    let later = plain.state()?.context("state")?;
    assert_eq!(later["bytes_in"], received, "{later}");
    let status = plain.eval("document.getElementById('status').textContent")?;
    assert!(
        status.as_str().is_some_and(|t| !t.contains("fps")),
        "{status}"
    );
    server.stop()
}

/// The page keeps working across a server restart: it reconnects, resumes, and shows edits
/// made after the restart.
#[test]
fn the_page_reconnects_and_resumes_across_a_restart() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let server = TestServer::start(dir.path(), local())?;
    let addr = server.addr;
    let mut browser = Browser::start(320, 180)?;
    browser.goto(&viewer_url(&server, "demo"))?;
    browser.wait_state("s.synced && s.connects === 1", 60_000)?;
    server.stop()?;
    browser.wait_state("s.status === 'reconnecting'", 30_000)?;
    let server = TestServer::start(dir.path(), addr)?;
    let state = browser.wait_state("s.status === 'live' && s.connects >= 2", 30_000)?;
    println!("after the restart: {state}");
    let pos = [3, 60, 3];
    let seq = native_edit(
        &server,
        vec![EditOp::Set {
            pos,
            colour: Colour::from_rgb8(0, 0, 255),
        }],
    )?;
    browser.wait_state(&format!("s.seq >= {seq}"), 30_000)?;
    let page_state = browser.state()?.context("state")?;
    assert_eq!(page_state["status"], "live", "{page_state}");
    let frame = browser.trace(5, 5, [3.5, 63.5, 3.5], [3.5, 0.0, 3.51], 30.0)?;
    assert_eq!(
        frame.hits[12],
        Some(pos),
        "the page shows the edit made after the restart"
    );
    server.stop()
}
