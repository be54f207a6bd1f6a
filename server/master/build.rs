//! Bundles the browser libraries the pages load from npm (A-Frame for the headset page,
//! holoplay-core for Looking Glass displays) into the binary, so `nephele serve` runs from
//! anywhere. They come from `web/node_modules` (`npm ci --prefix web`, run here when npm is
//! present and they are missing); never from a CDN. Without npm the build still succeeds:
//! each missing file is replaced by a one-line script that tells the page, in words, what
//! to install, and the viewer and AR pages (which need neither) work as before.
//!
//! It also warns when `nasm` is missing: `openh264-sys2` then builds OpenH264 without its x86
//! assembly, silently, and the encoder is about 2× slower (`bench encode`).

use std::{path::Path, process::Command};

/// (URL name under /vendor/, file under web/node_modules).
const VENDOR: &[(&str, &str)] = &[
    ("aframe.min.js", "aframe/dist/aframe-v1.8.0.min.js"),
    ("holoplay-core.min.js", "holoplay-core/dist/holoplaycore.min.js"),
];

fn main() {
    let manifest = std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets it");
    let web = Path::new(&manifest).join("../../web");
    let modules = web.join("node_modules");
    println!("cargo:rerun-if-changed={}", web.join("package-lock.json").display());
    println!("cargo:rerun-if-env-changed=NEPHELE_NO_NPM");
    let missing = VENDOR.iter().any(|(_, f)| !modules.join(f).exists());
    if missing && std::env::var_os("NEPHELE_NO_NPM").is_none() {
        let status = Command::new("npm").args(["ci", "--no-audit", "--no-fund", "--prefix"]).arg(&web).status();
        match status {
            Ok(s) if s.success() => {}
            Ok(s) => println!("cargo:warning=`npm ci --prefix web` failed ({s}); vr.html and quilt.html will say what to install"),
            Err(e) => println!("cargo:warning=npm is not available ({e}); vr.html and quilt.html will say what to install"),
        }
    }
    let nasm = Command::new("nasm").arg("-v").output();
    if !nasm.is_ok_and(|o| o.status.success()) && std::env::var("CARGO_CFG_TARGET_ARCH").is_ok_and(|a| a == "x86_64" || a == "x86") {
        println!("cargo:warning=nasm is not installed: OpenH264 builds without its assembly and encodes ~2x slower; `apt-get install nasm`, then `cargo clean --release -p openh264-sys2` and rebuild");
    }
    let out = Path::new(&std::env::var("OUT_DIR").expect("cargo sets it")).join("vendor");
    std::fs::create_dir_all(&out).expect("creating OUT_DIR/vendor");
    for (name, file) in VENDOR {
        let src = modules.join(file);
        println!("cargo:rerun-if-changed={}", src.display());
        let body = std::fs::read(&src).unwrap_or_else(|_| {
            let words = format!(
                "{name} was not built into this server: install Node.js and npm, run `npm ci --prefix web` in the Nephele repository, and rebuild"
            );
            format!("window.NEPHELE_VENDOR_MISSING = (window.NEPHELE_VENDOR_MISSING ? window.NEPHELE_VENDOR_MISSING + '; ' : '') + {words:?};\n").into_bytes()
        });
        std::fs::write(out.join(name), body).expect("writing the vendor file");
    }
}
