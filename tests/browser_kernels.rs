//! Every kernel variant compiles in a browser: the composed WGSL of each key (both
//! storages, every walk, query, counters, one mesh or two levels) goes to headless Chromium's WebGPU (Tint, the compiler Chrome uses,
//! on SwiftShader), which compiles the module and builds the pipeline with the key's
//! override constants. naga accepting the WGSL is not enough: Tint also applies WGSL's
//! rules on constant expressions and uniformity. Any compiler message or pipeline error
//! fails the test, naming the key.
//!
//! Needs Debian's `chromium` (installed by `.ci/run`); without it the test prints SKIP.
//! `BVHTRACE_CHROMIUM` names another binary.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use bvhtrace_gpu::kernels::{BvhStorage, DriverTuning, KernelKey};

/// The variants: every walk, query, counters setting, one mesh or two levels, with the
/// BVH in buffers (what a page on WebGPU composes) and in textures.
fn variants() -> Vec<KernelKey> {
    [BvhStorage::Buffers, BvhStorage::Textures]
        .into_iter()
        .flat_map(|storage| KernelKey::all_for_k(storage, 6))
        .collect()
}

/// The page: compiles each variant with `getCompilationInfo`, builds its pipeline, and
/// writes one line per variant (`ok NAME` or `error NAME: MESSAGE`) into `<pre id=out>`.
fn page(keys: &[KernelKey]) -> String {
    let tuning = DriverTuning::GPU.constants();
    let list: Vec<serde_json::Value> = keys
        .iter()
        .map(|k| {
            let constants: serde_json::Map<String, serde_json::Value> = (k.constants().into_iter())
                .chain(tuning)
                .map(|(name, v)| (name.to_string(), v.into()))
                .collect();
            serde_json::json!({
                "name": format!("{k:?}"),
                "source": k.source(),
                "entry": k.entry_point(),
                "constants": constants,
            })
        })
        .collect();
    format!(
        r#"<!doctype html><meta charset="utf-8"><pre id="out">running</pre><script>
const variants = {};
(async () => {{
  const out = [];
  try {{
    const adapter = await navigator.gpu.requestAdapter();
    const l = adapter.limits;
    const device = await adapter.requestDevice({{ requiredLimits: {{
      maxStorageBuffersPerShaderStage: l.maxStorageBuffersPerShaderStage,
      maxStorageTexturesPerShaderStage: l.maxStorageTexturesPerShaderStage,
      maxComputeWorkgroupStorageSize: l.maxComputeWorkgroupStorageSize,
    }} }});
    out.push(`adapter ${{adapter.info.vendor}} ${{adapter.info.architecture}}`);
    const modules = new Map();
    for (const v of variants) {{
      device.pushErrorScope("validation");
      // Variants differing only in override constants share one module.
      if (!modules.has(v.source)) {{
        const module = device.createShaderModule({{ code: v.source }});
        const info = await module.getCompilationInfo();
        modules.set(v.source, [module, info.messages.filter(m => m.type === "error")
          .map(m => `${{m.lineNum}}:${{m.linePos}} ${{m.message}}`)]);
      }}
      const [module, compiled] = modules.get(v.source);
      const errors = [...compiled];
      let pipeline = "";
      try {{
        await device.createComputePipelineAsync({{ layout: "auto",
          compute: {{ module, entryPoint: v.entry, constants: v.constants }} }});
      }} catch (e) {{ pipeline = String(e.message || e); }}
      const scope = await device.popErrorScope();
      if (scope) errors.push(scope.message);
      if (pipeline) errors.push(pipeline);
      out.push(errors.length ? `error ${{v.name}}: ${{errors.join(" | ")}}` : `ok ${{v.name}}`);
    }}
  }} catch (e) {{ out.push(`error page: ${{e}}`); }}
  out.push("done");
  document.getElementById("out").textContent = out.join("\n");
  await fetch("/result", {{ method: "POST", body: out.join("\n") }});
}})();
</script>"#,
        serde_json::Value::Array(list)
    )
}

/// Serves `page` on 127.0.0.1 (a secure context, as WebGPU wants) and sends the body of
/// each `POST /result` to the returned channel.
fn serve(page: String) -> (u16, mpsc::Receiver<String>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("a local port");
    let port = listener.local_addr().expect("its address").port();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let mut reader = BufReader::new(&stream);
            let (mut request, mut line, mut length) = (String::new(), String::new(), 0);
            let _ = reader.read_line(&mut request);
            while reader.read_line(&mut line).is_ok_and(|n| n > 2) {
                if let Some(v) = line.to_ascii_lowercase().strip_prefix("content-length:") {
                    length = v.trim().parse().unwrap_or(0);
                }
                line.clear();
            }
            let mut body = vec![0; length];
            let _ = reader.read_exact(&mut body);
            let reply = match request.starts_with("POST") {
                true => {
                    let _ = tx.send(String::from_utf8_lossy(&body).into_owned());
                    String::new()
                }
                false => page.clone(),
            };
            let mut s = &stream;
            let head = format!(
                "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                reply.len()
            );
            let _ = s
                .write_all(head.as_bytes())
                .and_then(|_| s.write_all(reply.as_bytes()));
        }
    });
    (port, rx)
}

#[test]
fn every_kernel_variant_compiles_in_chromium() {
    let chromium = std::env::var("BVHTRACE_CHROMIUM").unwrap_or_else(|_| "chromium".into());
    if Command::new(&chromium).arg("--version").output().is_err() {
        eprintln!("SKIP every_kernel_variant_compiles_in_chromium: no {chromium} installed");
        return;
    }
    let keys = variants();
    let (port, results) = serve(page(&keys));
    let profile = std::env::temp_dir().join(format!("bvhtrace-chromium-{}", std::process::id()));
    let mut child = Command::new(&chromium)
        .args([
            "--headless=new",
            "--no-sandbox",
            "--enable-unsafe-webgpu",
            "--use-webgpu-adapter=swiftshader",
            "--enable-unsafe-swiftshader",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("http://127.0.0.1:{port}/"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("chromium starts");
    // A hung page fails the test instead of hanging it.
    let report = results.recv_timeout(Duration::from_secs(600));
    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_dir_all(&profile);
    let dom = report.expect("the page reported within 10 minutes");
    let lines: Vec<&str> = dom.lines().collect();
    let first = lines.iter().position(|l| l.contains("adapter "));
    eprintln!("{}", first.map_or("no adapter line", |i| lines[i]));
    let ok = lines.iter().filter(|l| l.starts_with("ok ")).count();
    let errors: Vec<&&str> = lines.iter().filter(|l| l.starts_with("error ")).collect();
    assert!(
        errors.is_empty(),
        "{} of {} variants failed in Chromium:\n{}",
        errors.len(),
        keys.len(),
        errors
            .iter()
            .map(|e| e.chars().take(600).collect::<String>())
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert!(
        lines.iter().any(|l| l.trim_end().ends_with("done")),
        "the page did not finish:\n{dom}"
    );
    assert_eq!(ok, keys.len(), "variants compiled");
    eprintln!("browser kernels: {ok} variants compile in Chromium");
}
