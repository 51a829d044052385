//! Checks that a Rust struct uploaded as a uniform mirrors the WGSL struct
//! its shader declares: the same size, and each WGSL member at the offset
//! of the Rust field of the same name (members whose names start with `_`
//! are padding and only count towards the size). WGSL lays a uniform out by
//! its own rules (a `vec3<f32>` aligned to 16 bytes, a struct's size
//! rounded to its alignment), so a field added on one side only, or in
//! another order, shifts every value after it without any error from the
//! driver; naga's reflection of the shader says where each member is.

/// The struct declarations and module constants of `source` (a shader file
/// or any text holding the struct), alone, so that one file's structs can
/// be reflected without the functions it needs from other files.
fn declarations(source: &str) -> String {
    let mut out = String::new();
    let mut inside = false;
    for line in source.lines() {
        if line.starts_with("struct ") {
            inside = true;
        }
        if inside || line.starts_with("const ") {
            out.push_str(line);
            out.push('\n');
        }
        if inside && line.starts_with('}') {
            inside = false;
        }
    }
    out
}

/// Whether the WGSL struct must hold every Rust field, or may declare only
/// the leading ones a shader reads (several shaders share one uniform).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Extent {
    Whole,
    Prefix,
}

/// Panics naming the member when `rust_fields` (name, byte offset) and
/// `rust_size` do not mirror `wgsl_struct` in `source`.
pub fn check(
    source: &str,
    wgsl_struct: &str,
    rust_size: usize,
    rust_fields: &[(&str, usize)],
    extent: Extent,
) {
    let text = declarations(source);
    let module = naga::front::wgsl::parse_str(&text)
        .unwrap_or_else(|e| panic!("the declarations do not parse: {e}\n{text}"));
    let (members, span) = module
        .types
        .iter()
        .find_map(|(_, ty)| match &ty.inner {
            naga::TypeInner::Struct { members, span }
                if ty.name.as_deref() == Some(wgsl_struct) =>
            {
                Some((members.clone(), *span as usize))
            }
            _ => None,
        })
        .unwrap_or_else(|| panic!("no struct {wgsl_struct} in the shader"));
    for member in &members {
        let name = member.name.as_deref().unwrap_or("");
        if name.starts_with('_') {
            continue;
        }
        let Some(&(_, offset)) = rust_fields.iter().find(|(n, _)| *n == name) else {
            panic!(
                "{wgsl_struct}.{name} (byte {}) has no Rust field of that name",
                member.offset
            );
        };
        assert_eq!(
            offset, member.offset as usize,
            "{wgsl_struct}.{name}: byte {offset} in Rust, {} in WGSL",
            member.offset
        );
    }
    if extent == Extent::Prefix {
        assert!(
            rust_size >= span,
            "{wgsl_struct}: {rust_size} bytes in Rust, fewer than WGSL's {span}"
        );
        return;
    }
    for (name, _) in rust_fields {
        assert!(
            members.iter().any(|m| m.name.as_deref() == Some(name)),
            "the Rust field {name} has no member in WGSL's {wgsl_struct}"
        );
    }
    assert_eq!(
        rust_size, span,
        "{wgsl_struct}: {rust_size} bytes in Rust, {span} in WGSL"
    );
}

/// `assert_mirrors!(SHADER_SOURCE, "WgslName", RustType, [field, ...])`:
/// every field of the Rust type but its padding. With `prefix` after the
/// list, the shader may declare only the leading fields.
macro_rules! assert_mirrors {
    ($source:expr, $wgsl:literal, $rust:ty, [$($field:ident),* $(,)?]) => {
        assert_mirrors!(@check $source, $wgsl, $rust, [$($field),*], Whole)
    };
    ($source:expr, $wgsl:literal, $rust:ty, [$($field:ident),* $(,)?], prefix) => {
        assert_mirrors!(@check $source, $wgsl, $rust, [$($field),*], Prefix)
    };
    (@check $source:expr, $wgsl:literal, $rust:ty, [$($field:ident),*], $extent:ident) => {
        $crate::engine::gpu::mirror::check(
            $source,
            $wgsl,
            std::mem::size_of::<$rust>(),
            &[$((stringify!($field), std::mem::offset_of!($rust, $field))),*],
            $crate::engine::gpu::mirror::Extent::$extent,
        )
    };
}
pub(crate) use assert_mirrors;

#[cfg(test)]
mod tests {
    #[repr(C)]
    struct Mirror {
        count: u32,
        _pad: [u32; 3],
        centre: [f32; 3],
        scale: f32,
    }

    const SHADER: &str = "
const N: u32 = 2u;
struct Params {
    count: u32,
    centre: vec3<f32>,
    scale: f32,
}
@group(0) @binding(0) var<uniform> params: Params;
fn unrelated() -> f32 { return params.scale; }
";

    #[test]
    fn a_true_mirror_passes() {
        assert_mirrors!(SHADER, "Params", Mirror, [count, centre, scale]);
    }

    /// `centre` is a vec3: WGSL aligns it to 16 bytes, so a Rust mirror
    /// without the padding before it is caught.
    #[test]
    #[should_panic(expected = "Params.centre: byte 4 in Rust, 16 in WGSL")]
    fn a_field_at_the_wrong_offset_is_named() {
        #[repr(C)]
        struct Packed {
            count: u32,
            centre: [f32; 3],
            scale: f32,
            _pad: [u32; 3],
        }
        assert_mirrors!(SHADER, "Params", Packed, [count, centre, scale]);
    }

    #[test]
    #[should_panic(expected = "Params.scale (byte 28) has no Rust field of that name")]
    fn a_missing_field_is_named() {
        assert_mirrors!(SHADER, "Params", Mirror, [count, centre]);
    }
}
