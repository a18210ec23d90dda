//! Shipping and archiving a shard set as one zstd-compressed file (`voxrad-shard pack` and
//! `unpack`).
//!
//! ```text
//! a zstd stream whose decompressed bytes are:
//!   magic      8 bytes  "VXRPACK\0"
//!   version    u32      1
//!   files      u32      number of files (the manifest and the shards)
//!   per file:  name_len u16, name (UTF-8, a plain file name), size u64, then size bytes
//!   end magic  8 bytes  "VXRPEND\0"
//! ```
//!
//! Besides zstd's content checksum, every shard and the manifest carry their own: `pack` checks
//! them as it copies (a damaged set is refused, not archived as if it were good), and `unpack`
//! verifies the whole set (`shardset::verify_set`) in its staging directory before it
//! moves it into place, so a damaged pack never becomes a shard set. Both directions stream
//! through fixed buffers; nothing grows with the set.

use super::shardset::{verify_set, Staging};
use super::ConvertError;
use crate::storage::shard::FOOTER_LEN;
use crate::storage::{Manifest, MANIFEST_FILE};
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::Path;

const MAGIC: &[u8; 8] = b"VXRPACK\0";
const END_MAGIC: &[u8; 8] = b"VXRPEND\0";
const VERSION: u32 = 1;
/// zstd level: 3 (the library's default) compresses shard records about 3x at disk speed.
const LEVEL: i32 = 3;
const BUFFER: usize = 1 << 20;

fn bad(path: &Path, what: impl std::fmt::Display) -> ConvertError {
    ConvertError::BadInput(format!("{}: {what}", path.display()))
}

fn failed(path: &Path, what: impl std::fmt::Display) -> ConvertError {
    ConvertError::Failure(format!("{}: {what}", path.display()))
}

/// What a pack or unpack moved.
#[derive(Clone, Copy, Debug)]
pub struct Packed {
    pub files: usize,
    /// Bytes of the shard set's files, and of the pack.
    pub set_bytes: u64,
    pub pack_bytes: u64,
}

/// Packs the shard set `set` into the file `out` (written under a temporary name, renamed when
/// complete).
pub fn pack(set: &Path, out: &Path) -> Result<Packed, ConvertError> {
    let manifest = Manifest::read_dir(set)?;
    let readers = manifest.check_shards(set)?;
    let mut names = vec![MANIFEST_FILE.to_string()];
    names.extend(manifest.shards.iter().map(|s| s.file.clone()));
    let tmp = crate::output::atomic::temp_beside(out).map_err(|e| failed(out, e))?;
    let writer = BufWriter::with_capacity(BUFFER, tmp);
    let mut z = zstd::Encoder::new(writer, LEVEL).map_err(|e| failed(out, e))?;
    // zstd's own checksum of the content as well: a damaged pack is named as such at once,
    // before the verification of the files would catch it.
    z.include_checksum(true).map_err(|e| failed(out, e))?;
    let io = |e: std::io::Error| failed(out, e);
    z.write_all(MAGIC).map_err(io)?;
    z.write_all(&VERSION.to_le_bytes()).map_err(io)?;
    z.write_all(&(names.len() as u32).to_le_bytes())
        .map_err(io)?;
    let mut set_bytes = 0;
    let mut buf = vec![0u8; BUFFER];
    for (k, name) in names.iter().enumerate() {
        // The manifest's checksum was checked on reading it; a shard's is checked on the bytes
        // copied, which are all the bytes before its footer.
        let shard = k.checked_sub(1).map(|i| &readers[i]);
        let body = shard.map_or(0, |r| r.info().bytes - FOOTER_LEN);
        let mut hasher = crc32fast::Hasher::new();
        let path = set.join(name);
        let mut file = File::open(&path).map_err(|e| bad(&path, format!("cannot read: {e}")))?;
        let size = file.metadata().map_err(|e| failed(&path, e))?.len();
        z.write_all(&(name.len() as u16).to_le_bytes())
            .map_err(io)?;
        z.write_all(name.as_bytes()).map_err(io)?;
        z.write_all(&size.to_le_bytes()).map_err(io)?;
        let mut left = size;
        while left > 0 {
            let n = (left as usize).min(BUFFER);
            file.read_exact(&mut buf[..n])
                .map_err(|e| failed(&path, format!("changed while being packed: {e}")))?;
            let offset = size - left;
            if offset < body {
                hasher.update(&buf[..(body - offset).min(n as u64) as usize]);
            }
            z.write_all(&buf[..n]).map_err(io)?;
            left -= n as u64;
        }
        if let Some(reader) = shard {
            reader.compare_checksum(hasher.finalize())?;
        }
        set_bytes += size;
    }
    z.write_all(END_MAGIC).map_err(io)?;
    let writer = z.finish().map_err(io)?;
    let tmp = writer.into_inner().map_err(|e| failed(out, e.error()))?;
    crate::output::atomic::commit(tmp, out).map_err(|e| failed(out, e))?;
    let pack_bytes = std::fs::metadata(out).map_err(|e| failed(out, e))?.len();
    Ok(Packed {
        files: names.len(),
        set_bytes,
        pack_bytes,
    })
}

/// Unpacks `pack` into the shard set directory `out` (new, empty, or a shard set to replace),
/// verifying every file before the set is moved into place.
pub fn unpack(pack: &Path, out: &Path) -> Result<Packed, ConvertError> {
    let file = File::open(pack).map_err(|e| bad(pack, format!("cannot read: {e}")))?;
    let pack_bytes = file.metadata().map_err(|e| failed(pack, e))?.len();
    let staging = Staging::new(out)?;
    let damaged = |what: &str| bad(pack, format!("is not a complete voxrad pack: {what}"));
    let mut z =
        zstd::Decoder::new(BufReader::with_capacity(BUFFER, file)).map_err(|e| failed(pack, e))?;
    let mut read = |buf: &mut [u8], what: &str| {
        z.read_exact(buf)
            .map_err(|e| damaged(&format!("{what} ({e})")))
    };
    let mut head = [0u8; 16];
    read(&mut head, "header")?;
    if &head[..8] != MAGIC {
        return Err(bad(
            pack,
            "is not a voxrad pack (wrong magic); check the path",
        ));
    }
    let version = u32::from_le_bytes([head[8], head[9], head[10], head[11]]);
    if version != VERSION {
        return Err(bad(
            pack,
            format!("has pack version {version}; this build reads version {VERSION}"),
        ));
    }
    let files = u32::from_le_bytes([head[12], head[13], head[14], head[15]]) as usize;
    let mut set_bytes = 0;
    let mut buf = vec![0u8; BUFFER];
    for _ in 0..files {
        let mut len = [0u8; 2];
        read(&mut len, "file name length")?;
        let mut name = vec![0u8; u16::from_le_bytes(len) as usize];
        read(&mut name, "file name")?;
        let name = String::from_utf8(name).map_err(|_| damaged("a file name is not UTF-8"))?;
        // Only plain names: a pack must not write outside its directory.
        if name.is_empty() || name.contains(['/', '\\']) || name == "." || name == ".." {
            return Err(damaged(&format!(
                "file name {name:?} is not a plain file name"
            )));
        }
        let mut size = [0u8; 8];
        read(&mut size, "file size")?;
        let size = u64::from_le_bytes(size);
        let path = staging.path().join(&name);
        let mut w =
            BufWriter::with_capacity(BUFFER, File::create(&path).map_err(|e| failed(&path, e))?);
        let mut left = size;
        while left > 0 {
            let n = (left as usize).min(BUFFER);
            read(&mut buf[..n], &format!("contents of {name}"))?;
            w.write_all(&buf[..n]).map_err(|e| failed(&path, e))?;
            left -= n as u64;
        }
        w.flush().map_err(|e| failed(&path, e))?;
        w.get_ref().sync_all().map_err(|e| failed(&path, e))?;
        set_bytes += size;
    }
    let mut end = [0u8; 8];
    read(&mut end, "end marker")?;
    if &end != END_MAGIC {
        return Err(damaged("the end marker is wrong"));
    }
    // Reading on to the end of the stream makes zstd check its content checksum.
    let mut rest = Vec::new();
    z.read_to_end(&mut rest)
        .map_err(|e| damaged(&format!("its compressed data is corrupted ({e})")))?;
    if !rest.is_empty() {
        return Err(damaged("there are bytes after the end marker"));
    }
    // Every checksum, the order and the manifest, before the set becomes visible.
    verify_set(staging.path()).map_err(|e| match e {
        ConvertError::BadInput(m) => damaged(&m),
        other => other,
    })?;
    staging.commit()?;
    Ok(Packed {
        files,
        set_bytes,
        pack_bytes,
    })
}
