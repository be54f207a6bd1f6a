//! Every WGSL kernel parses and validates with naga (no GPU needed), and the Rust mirrors of
//! its structs have the sizes naga computes.

use nephele_renderer::gpu::{GpuView, HIT_BYTES, Params, compose::{COMPOSE_WGSL, ComposeParams}, kernel_sources};

#[test]
fn kernels_validate_and_structs_match() {
    for (name, src) in kernel_sources() {
        let module = naga::front::wgsl::parse_str(&src).unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(&src)));
        let mut validator = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
        let info = validator.validate(&module).unwrap_or_else(|e| panic!("{name}: {e:?}"));
        drop(info);
        let size_of = |ty: &str| {
            let (h, _) = module.types.iter().find(|(_, t)| t.name.as_deref() == Some(ty)).unwrap();
            module.types[h].inner.size(module.to_ctx())
        };
        assert_eq!(size_of("Params") as usize, std::mem::size_of::<Params>(), "{name}: Params");
        assert_eq!(size_of("View") as usize, std::mem::size_of::<GpuView>(), "{name}: View");
        assert_eq!(size_of("Hit") as u64, HIT_BYTES, "{name}: Hit");
    }
}

#[test]
fn compose_kernel_validates_and_its_params_match() {
    let module = naga::front::wgsl::parse_str(COMPOSE_WGSL).unwrap_or_else(|e| panic!("{}", e.emit_to_string(COMPOSE_WGSL)));
    let mut validator = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
    validator.validate(&module).unwrap_or_else(|e| panic!("{e:?}"));
    let (h, _) = module.types.iter().find(|(_, t)| t.name.as_deref() == Some("ComposeParams")).unwrap();
    assert_eq!(module.types[h].inner.size(module.to_ctx()) as usize, std::mem::size_of::<ComposeParams>());
}
