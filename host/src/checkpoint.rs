//! Versioned checkpoint container.
//!
//! A checkpoint is opaque to this module: the trainer puts its own encoded configuration in
//! `config` and its parameter, optimizer and RNG state in named `sections`. This module only
//! guarantees that what was saved is what is loaded, and says clearly why a file is refused.
//!
//! File layout (all integers little-endian):
//!
//! | bytes | content |
//! | --- | --- |
//! | 8 | magic `ORBNERF\x01`, which tells a checkpoint from any other file |
//! | 4 | format version (`u32`), bumped whenever the payload encoding changes |
//! | 8 | payload length in bytes (`u64`) |
//! | 4 | CRC-32 (IEEE) of the payload (`u32`) |
//! | n | payload: the [`Checkpoint`] encoded with postcard |
//!
//! The length and checksum come before the payload so that a truncated or corrupted file is
//! caught before postcard sees it (postcard would otherwise report a confusing decode error, or
//! worse, decode a flipped bit into a different but well-formed value).

use crate::error::{HostError, Result};
use crate::io::write_atomic_with;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// First bytes of every checkpoint file.
pub const MAGIC: [u8; 8] = *b"ORBNERF\x01";
/// The payload encoding this build writes and the only one it reads. Version 3: the density
/// and the learned pose translations are in units of the scene box (`Config::length_unit`),
/// so a version 2 model of a box other than [-1.5, 1.5]³ would render differently. Version 4:
/// the config gained `plane_tv_weight` and `coarse_to_fine_steps` (configs are encoded by
/// field position). Version 5: the config gained the pose prior and refinement fields, and
/// the training state the pose corrections' own update count. Version 6: the config gained
/// `ray_store`, `loss_weighted_frames` and `lr_decay_start`, the training state the ray
/// reservoir's counts and each frame slot's metadata its running loss. Version 7: a stream
/// checkpoint's `stream` section gained the settle (its settings' `settle_steps` and the
/// step it began at); a training checkpoint differs from version 6 only in this number.
/// Version 8: the `stream` section gained whether the settle plans the learning rate anew
/// (`StreamState::decay_over_settle`); a training checkpoint differs only in this number.
/// Version 9: a ray reservoir's entries are 4 bytes (colour and mask) in one run per frame,
/// and each frame slot's metadata holds its runs (`FrameMeta::rays`).
pub const FORMAT_VERSION: u32 = 9;
/// Magic + version + payload length + CRC-32.
pub const HEADER_LEN: usize = MAGIC.len() + 4 + 8 + 4;

/// The contents of a checkpoint file: who wrote it, its configuration and its named state.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// What wrote the checkpoint (e.g. the trainer's name), so a reader can refuse a foreign one.
    pub kind: String,
    /// The writer's own encoded configuration.
    pub config: Vec<u8>,
    /// Named blobs (parameters, optimizer moments, RNG state...). Names are unique.
    pub sections: Vec<Section>,
}

/// One named blob of a [`Checkpoint`], opaque to this module.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Section {
    /// The name the writer looks it up by, unique within the checkpoint.
    pub name: String,
    /// The writer's encoding of the state.
    pub bytes: Vec<u8>,
}

impl Checkpoint {
    /// The bytes of the section called `name`, or an error listing the sections there are.
    pub fn section(&self, name: &str) -> Result<&[u8]> {
        match self.sections.iter().find(|s| s.name == name) {
            Some(section) => Ok(&section.bytes),
            None => {
                let names: Vec<&str> = self.sections.iter().map(|s| s.name.as_str()).collect();
                Err(HostError::invalid(
                    format!("checkpoint of kind `{}`", self.kind),
                    format!("no section named `{name}` (it has: {})", names.join(", ")),
                ))
            }
        }
    }

    fn duplicate_section_name(&self) -> Option<&str> {
        self.sections.iter().enumerate().find_map(|(i, s)| {
            self.sections[..i]
                .iter()
                .any(|earlier| earlier.name == s.name)
                .then_some(s.name.as_str())
        })
    }
}

/// Encode `checkpoint` and write it to `path` atomically (a crash never leaves half a file).
/// Refuses duplicate section names, which would make [`Checkpoint::section`] ambiguous.
pub fn save(path: &Path, checkpoint: &Checkpoint) -> Result<()> {
    let sections: Vec<(&str, &[u8])> = (checkpoint.sections.iter())
        .map(|s| (s.name.as_str(), s.bytes.as_slice()))
        .collect();
    save_parts(path, &checkpoint.kind, &checkpoint.config, &sections)
}

/// [`save`] of a checkpoint's parts where they lie (a trainer's arena, say): the payload is
/// streamed to the file in postcard's encoding of a [`Checkpoint`], its length and checksum
/// computed first, so saving takes no second copy of the model (a run never loses its
/// training to an allocation at the end).
pub fn save_parts(
    path: &Path,
    kind: &str,
    config: &[u8],
    sections: &[(&str, &[u8])],
) -> Result<()> {
    if let Some(i) =
        (1..sections.len()).find(|&i| sections[..i].iter().any(|s| s.0 == sections[i].0))
    {
        return Err(HostError::invalid(
            path,
            format!("two sections are named `{}`", sections[i].0),
        ));
    }
    // The payload as postcard lays out a `Checkpoint`: each string and byte vector as a
    // varint length and its bytes, the sections as a varint count and each section.
    let mut pieces: Vec<&[u8]> = Vec::with_capacity(4 * sections.len() + 4);
    let mut lengths: Vec<[u8; 10]> = Vec::with_capacity(2 * sections.len() + 3);
    lengths.extend([kind.len(), config.len(), sections.len()].map(varint));
    for (name, bytes) in sections {
        lengths.extend([name.len(), bytes.len()].map(varint));
    }
    pieces.extend([varint_bytes(&lengths[0]), kind.as_bytes()]);
    pieces.extend([varint_bytes(&lengths[1]), config]);
    pieces.push(varint_bytes(&lengths[2]));
    for (k, (name, bytes)) in sections.iter().enumerate() {
        pieces.extend([varint_bytes(&lengths[3 + 2 * k]), name.as_bytes()]);
        pieces.extend([varint_bytes(&lengths[4 + 2 * k]), *bytes]);
    }
    let mut crc = crc32fast::Hasher::new();
    let mut payload_len = 0u64;
    for piece in &pieces {
        crc.update(piece);
        payload_len += piece.len() as u64;
    }
    let crc = crc.finalize();
    write_atomic_with(path, |file| {
        file.write_all(&MAGIC)?;
        file.write_all(&FORMAT_VERSION.to_le_bytes())?;
        file.write_all(&payload_len.to_le_bytes())?;
        file.write_all(&crc.to_le_bytes())?;
        pieces.iter().try_for_each(|piece| file.write_all(piece))
    })
}

/// `n` as a LEB128 varint (postcard's encoding of lengths), in a 10-byte buffer.
fn varint(mut n: usize) -> [u8; 10] {
    let mut out = [0u8; 10];
    for byte in out.iter_mut() {
        *byte = (n & 0x7f) as u8;
        n >>= 7;
        if n == 0 {
            break;
        }
        *byte |= 0x80;
    }
    out
}

/// The bytes of a [`varint`] buffer in use: up to the first without the continuation bit.
fn varint_bytes(v: &[u8; 10]) -> &[u8] {
    &v[..v
        .iter()
        .position(|b| b & 0x80 == 0)
        .map_or(v.len(), |i| i + 1)]
}

/// Most bytes [`read_head`] reads: the header, the kind and an encoded config are far smaller.
const HEAD_BYTES: u64 = 1 << 16;

/// The kind and the writer's encoded config of the checkpoint at `path`, and the file's size,
/// from the head of the file alone: what a memory check needs before the whole file is read.
/// The checksum is verified only by [`load`].
pub fn read_head(path: &Path) -> Result<(String, Vec<u8>, u64)> {
    use std::io::Read;
    let file = std::fs::File::open(path).map_err(|e| HostError::io(path, e))?;
    let size = file.metadata().map_err(|e| HostError::io(path, e))?.len();
    let mut head = Vec::new();
    file.take(HEAD_BYTES)
        .read_to_end(&mut head)
        .map_err(|e| HostError::io(path, e))?;
    let refuse = |reason: &str| HostError::invalid(path, reason.to_string());
    if head.len() < HEADER_LEN || head[..MAGIC.len()] != MAGIC {
        // `load` says precisely what is wrong with such a file.
        return Err(decode(path, &head)
            .err()
            .unwrap_or_else(|| refuse("truncated")));
    }
    let version = u32::from_le_bytes(head[8..12].try_into().expect("4-byte slice"));
    if version != FORMAT_VERSION {
        return Err(refuse(&format!(
            "written by checkpoint format version {version}, this build reads version {FORMAT_VERSION}"
        )));
    }
    let (kind, config): (String, Vec<u8>) = postcard::take_from_bytes(&head[HEADER_LEN..])
        .map(|(head, _)| head)
        .map_err(|e| refuse(&format!("malformed payload: {e}")))?;
    Ok((kind, config, size))
}

/// Read and verify the checkpoint at `path`.
pub fn load(path: &Path) -> Result<Checkpoint> {
    let bytes = std::fs::read(path).map_err(|e| HostError::io(path, e))?;
    decode(path, &bytes)
}

/// [`load`] of a checkpoint file's bytes (`path` names it in errors).
///
/// ```
/// use orbit_nerf_host::checkpoint::{FORMAT_VERSION, MAGIC, decode};
/// use std::path::Path;
///
/// let path = Path::new("model.ckpt");
/// let foreign = decode(path, b"PNG and other things").unwrap_err().to_string();
/// assert!(foreign.contains("wrong magic bytes"), "{foreign}");
///
/// // The header of a checkpoint whose payload was cut off.
/// let mut cut = MAGIC.to_vec();
/// cut.extend(FORMAT_VERSION.to_le_bytes());
/// cut.extend(100u64.to_le_bytes()); // payload length
/// cut.extend(0u32.to_le_bytes()); // CRC-32
/// let truncated = decode(path, &cut).unwrap_err().to_string();
/// assert!(truncated.contains("truncated"), "{truncated}");
/// ```
pub fn decode(path: &Path, bytes: &[u8]) -> Result<Checkpoint> {
    let refuse = |reason: String| HostError::invalid(PathBuf::from(path), reason);
    // A file shorter than the magic that starts like one is a cut-off checkpoint, not a
    // foreign file.
    let magic_len = MAGIC.len().min(bytes.len());
    if bytes[..magic_len] != MAGIC[..magic_len] {
        return Err(refuse(
            "not an orbit-nerf checkpoint (wrong magic bytes)".into(),
        ));
    }
    if bytes.len() < HEADER_LEN {
        return Err(refuse(format!(
            "truncated: {} bytes, shorter than the {HEADER_LEN}-byte header",
            bytes.len()
        )));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4-byte slice"));
    if version != FORMAT_VERSION {
        return Err(refuse(format!(
            "written by checkpoint format version {version}, this build reads version {FORMAT_VERSION}"
        )));
    }
    let declared_len = u64::from_le_bytes(bytes[12..20].try_into().expect("8-byte slice"));
    let expected_crc = u32::from_le_bytes(bytes[20..24].try_into().expect("4-byte slice"));
    let payload = &bytes[HEADER_LEN..];
    if (payload.len() as u64) < declared_len {
        return Err(refuse(format!(
            "truncated: the header announces {declared_len} payload bytes, the file holds {}",
            payload.len()
        )));
    }
    if payload.len() as u64 > declared_len {
        return Err(refuse(format!(
            "{} unexpected bytes after the {declared_len}-byte payload",
            payload.len() as u64 - declared_len
        )));
    }
    let actual_crc = crc32fast::hash(payload);
    if actual_crc != expected_crc {
        return Err(refuse(format!(
            "checksum mismatch (stored {expected_crc:08x}, computed {actual_crc:08x}): the file is corrupt"
        )));
    }
    let (checkpoint, rest): (Checkpoint, &[u8]) = postcard::take_from_bytes(payload)
        .map_err(|e| refuse(format!("malformed payload: {e}")))?;
    if !rest.is_empty() {
        return Err(refuse(format!(
            "malformed payload: {} bytes left after decoding",
            rest.len()
        )));
    }
    if let Some(name) = checkpoint.duplicate_section_name() {
        return Err(refuse(format!(
            "malformed payload: two sections are named `{name}`"
        )));
    }
    Ok(checkpoint)
}

/// A checkpoint read section by section, each straight into where it belongs (a trainer's
/// arena, say): the file's length and checksum are verified first with a fixed buffer, then
/// the payload is walked in order, so restoring a model takes no copy of it in memory.
pub struct SectionReader<R> {
    path: PathBuf,
    source: R,
    /// Payload bytes not yet read.
    left: u64,
    /// Sections not yet announced by [`SectionReader::next_section`].
    sections_left: u64,
    /// Bytes of the section announced last that are not yet read.
    pending: u64,
    /// What wrote the checkpoint.
    pub kind: String,
    /// The writer's own encoded configuration.
    pub config: Vec<u8>,
}

/// Bytes read at a time while the checksum is verified.
const CHECKSUM_BUFFER: usize = 1 << 20;

impl SectionReader<std::io::BufReader<std::fs::File>> {
    /// Open and verify the checkpoint file at `path` ([`SectionReader::new`]).
    pub fn open(path: &Path) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|e| HostError::io(path, e))?;
        SectionReader::new(path, std::io::BufReader::new(file))
    }
}

impl<R: std::io::Read + std::io::Seek> SectionReader<R> {
    /// Verify the checkpoint in `source` (magic, version, length, checksum), refusing a bad
    /// one with the message [`load`] gives (`path` names it), and read its kind and config.
    pub fn new(path: &Path, mut source: R) -> Result<Self> {
        use std::io::{Read, SeekFrom};
        let io = |e| HostError::io(path, e);
        let size = source.seek(SeekFrom::End(0)).map_err(io)?;
        source.seek(SeekFrom::Start(0)).map_err(io)?;
        let mut head = Vec::with_capacity(HEADER_LEN);
        (&mut source)
            .take(HEADER_LEN as u64)
            .read_to_end(&mut head)
            .map_err(io)?;
        let version_ok = head.len() == HEADER_LEN
            && head[..MAGIC.len()] == MAGIC
            && head[8..12] == FORMAT_VERSION.to_le_bytes();
        if !version_ok {
            // A short, foreign or other-version file: `decode` says precisely what is wrong.
            return Err(decode(path, &head)
                .err()
                .unwrap_or_else(|| HostError::invalid(path, "truncated")));
        }
        let declared = u64::from_le_bytes(head[12..20].try_into().expect("8-byte slice"));
        let expected_crc = u32::from_le_bytes(head[20..24].try_into().expect("4-byte slice"));
        let held = size - HEADER_LEN as u64;
        if held < declared {
            return Err(HostError::invalid(
                path,
                format!(
                    "truncated: the header announces {declared} payload bytes, the file holds {held}"
                ),
            ));
        }
        if held > declared {
            return Err(HostError::invalid(
                path,
                format!(
                    "{} unexpected bytes after the {declared}-byte payload",
                    held - declared
                ),
            ));
        }
        let mut crc = crc32fast::Hasher::new();
        let mut buffer = vec![0u8; CHECKSUM_BUFFER];
        loop {
            let n = source.read(&mut buffer).map_err(io)?;
            if n == 0 {
                break;
            }
            crc.update(&buffer[..n]);
        }
        let actual_crc = crc.finalize();
        if actual_crc != expected_crc {
            return Err(HostError::invalid(
                path,
                format!(
                    "checksum mismatch (stored {expected_crc:08x}, computed {actual_crc:08x}): the file is corrupt"
                ),
            ));
        }
        source
            .seek(SeekFrom::Start(HEADER_LEN as u64))
            .map_err(io)?;
        let mut reader = SectionReader {
            path: path.to_path_buf(),
            source,
            left: declared,
            sections_left: 0,
            pending: 0,
            kind: String::new(),
            config: Vec::new(),
        };
        let kind = reader.read_small("kind")?;
        reader.kind = String::from_utf8(kind)
            .map_err(|_| reader.malformed("the kind is not UTF-8".into()))?;
        reader.config = reader.read_small("config")?;
        reader.sections_left = reader.varint()?;
        Ok(reader)
    }

    /// The next section's name and length in bytes (its bytes unread: read them with
    /// [`read_section`](Self::read_section), or they are skipped), or `None` after the last.
    pub fn next_section(&mut self) -> Result<Option<(String, u64)>> {
        if self.pending > 0 {
            let mut sink = std::io::sink();
            self.copy(self.pending, &mut sink)?;
            self.pending = 0;
        }
        if self.sections_left == 0 {
            if self.left > 0 {
                return Err(self.malformed(format!("{} bytes left after decoding", self.left)));
            }
            return Ok(None);
        }
        self.sections_left -= 1;
        let name = self.read_small("section name")?;
        let name = String::from_utf8(name)
            .map_err(|_| self.malformed("a section name is not UTF-8".into()))?;
        let len = self.varint()?;
        if len > self.left {
            return Err(self.malformed(format!(
                "section `{name}` announces {len} bytes, {} are left",
                self.left
            )));
        }
        self.pending = len;
        Ok(Some((name, len)))
    }

    /// Read the section announced last into `into`, which must be exactly its length.
    pub fn read_section(&mut self, into: &mut [u8]) -> Result<()> {
        if into.len() as u64 != self.pending {
            return Err(self.malformed(format!(
                "a section of {} bytes was read as {} bytes",
                self.pending,
                into.len()
            )));
        }
        self.source
            .read_exact(into)
            .map_err(|e| HostError::io(&self.path, e))?;
        self.left -= self.pending;
        self.pending = 0;
        Ok(())
    }

    /// The section announced last, read into a new buffer.
    pub fn read_section_vec(&mut self) -> Result<Vec<u8>> {
        let mut bytes = vec![0u8; self.pending as usize];
        self.read_section(&mut bytes)?;
        Ok(bytes)
    }

    /// The file (or name) the checkpoint is read from, for messages.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn malformed(&self, reason: String) -> HostError {
        HostError::invalid(&self.path, format!("malformed payload: {reason}"))
    }

    /// A postcard varint (LEB128) of the payload.
    fn varint(&mut self) -> Result<u64> {
        let mut value = 0u64;
        for shift in (0..70).step_by(7) {
            let mut byte = [0u8];
            self.take(&mut byte)?;
            let bits = (byte[0] & 0x7f) as u64;
            if shift == 63 && bits > 1 || shift > 63 {
                return Err(self.malformed("a length overflows".into()));
            }
            value |= bits << shift;
            if byte[0] & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err(self.malformed("a length overflows".into()))
    }

    /// A length-prefixed byte string of the head (kind, config, section name), which the
    /// writer keeps far below [`HEAD_BYTES`].
    fn read_small(&mut self, what: &str) -> Result<Vec<u8>> {
        let len = self.varint()?;
        if len > HEAD_BYTES || len > self.left {
            return Err(self.malformed(format!("the {what} announces {len} bytes")));
        }
        let mut bytes = vec![0u8; len as usize];
        self.take(&mut bytes)?;
        Ok(bytes)
    }

    /// Exactly `into.len()` payload bytes.
    fn take(&mut self, into: &mut [u8]) -> Result<()> {
        if into.len() as u64 > self.left {
            return Err(self.malformed("it ends inside a value".into()));
        }
        self.source
            .read_exact(into)
            .map_err(|e| HostError::io(&self.path, e))?;
        self.left -= into.len() as u64;
        Ok(())
    }

    /// `len` payload bytes copied into `sink`.
    fn copy(&mut self, len: u64, sink: &mut impl std::io::Write) -> Result<()> {
        let copied = std::io::copy(&mut std::io::Read::take(&mut self.source, len), sink)
            .map_err(|e| HostError::io(&self.path, e))?;
        if copied != len {
            return Err(self.malformed("it ends inside a section".into()));
        }
        self.left -= len;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Checkpoint {
        Checkpoint {
            kind: "kplanes-trainer".into(),
            config: vec![1, 2, 3, 250],
            sections: vec![
                Section {
                    name: "params".into(),
                    bytes: (0..=255).collect(),
                },
                Section {
                    name: "adam".into(),
                    bytes: vec![],
                },
                Section {
                    name: "rng".into(),
                    bytes: 0xDEAD_BEEF_u64.to_le_bytes().to_vec(),
                },
            ],
        }
    }

    fn saved(dir: &tempfile::TempDir) -> (PathBuf, Vec<u8>) {
        let path = dir.path().join("ck.bin");
        save(&path, &sample()).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        (path, bytes)
    }

    /// The streamed file is byte for byte the header and postcard's encoding of the whole
    /// checkpoint (lengths of one and two varint bytes, an empty section).
    #[test]
    fn a_streamed_save_is_postcards_encoding_with_its_header() {
        let dir = tempfile::tempdir().unwrap();
        let (_, bytes) = saved(&dir);
        let payload = postcard::to_stdvec(&sample()).unwrap();
        let mut expected = MAGIC.to_vec();
        expected.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        expected.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        expected.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
        expected.extend_from_slice(&payload);
        assert_eq!(bytes, expected);
        for n in [0usize, 127, 128, 16_383, 16_384, usize::MAX] {
            assert_eq!(
                varint_bytes(&varint(n)),
                postcard::to_stdvec(&n).unwrap(),
                "{n}"
            );
        }
    }

    /// The checkpoint at `path` read section by section with a [`SectionReader`].
    fn walk(path: &Path) -> Result<Checkpoint> {
        let mut reader = SectionReader::open(path)?;
        let mut sections = Vec::new();
        while let Some((name, _)) = reader.next_section()? {
            let bytes = reader.read_section_vec()?;
            sections.push(Section { name, bytes });
        }
        Ok(Checkpoint {
            kind: reader.kind,
            config: reader.config,
            sections,
        })
    }

    /// The errors of [`load`] and of [`walk`] on a file of `bytes`, both naming the file.
    fn load_err(path: &Path, bytes: &[u8]) -> Errors {
        std::fs::write(path, bytes).unwrap();
        let both = [
            load(path).unwrap_err().to_string(),
            walk(path).unwrap_err().to_string(),
        ];
        for message in &both {
            assert!(message.contains(&path.display().to_string()), "{message}");
        }
        Errors(both)
    }

    /// Two readers' messages for one file; `contains` holds when each says it.
    struct Errors([String; 2]);

    impl Errors {
        fn contains(&self, phrase: &str) -> bool {
            self.0.iter().all(|message| message.contains(phrase))
        }
    }

    impl std::fmt::Display for Errors {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "{} | {}", self.0[0], self.0[1])
        }
    }

    #[test]
    fn round_trips_and_finds_sections() {
        let dir = tempfile::tempdir().unwrap();
        let (path, bytes) = saved(&dir);
        assert_eq!(&bytes[..8], &MAGIC);
        let loaded = load(&path).unwrap();
        assert_eq!(loaded, sample());
        assert_eq!(walk(&path).unwrap(), sample());
        assert_eq!(
            loaded.section("rng").unwrap(),
            0xDEAD_BEEF_u64.to_le_bytes()
        );
        assert_eq!(loaded.section("adam").unwrap(), &[] as &[u8]);
        let missing = loaded.section("moments").unwrap_err().to_string();
        assert!(missing.contains("no section named `moments`"), "{missing}");
        assert!(missing.contains("params, adam, rng"), "{missing}");
    }

    #[test]
    fn missing_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("absent.ckpt");
        let message = load(&path).unwrap_err().to_string();
        assert!(message.contains("absent.ckpt"), "{message}");
    }

    #[test]
    fn wrong_magic() {
        let dir = tempfile::tempdir().unwrap();
        let (path, mut bytes) = saved(&dir);
        bytes[0] = b'P';
        assert!(load_err(&path, &bytes).contains("not an orbit-nerf checkpoint"));
        assert!(load_err(&path, b"{\"json\": true}").contains("not an orbit-nerf checkpoint"));
    }

    #[test]
    fn wrong_version() {
        let dir = tempfile::tempdir().unwrap();
        let (path, mut bytes) = saved(&dir);
        let other = FORMAT_VERSION + 1;
        bytes[8..12].copy_from_slice(&other.to_le_bytes());
        let message = load_err(&path, &bytes);
        assert!(
            message.contains(&format!(
                "format version {other}, this build reads version {FORMAT_VERSION}"
            )),
            "{message}"
        );
    }

    #[test]
    fn truncated_anywhere() {
        let dir = tempfile::tempdir().unwrap();
        let (path, bytes) = saved(&dir);
        for cut in [0, 3, 8, 23, 24, bytes.len() / 2, bytes.len() - 1] {
            let message = load_err(&path, &bytes[..cut]);
            assert!(message.contains("truncated"), "cut at {cut}: {message}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(load_err(&path, &longer).contains("unexpected bytes after"));
    }

    #[test]
    fn checksum_mismatch() {
        let dir = tempfile::tempdir().unwrap();
        let (path, mut bytes) = saved(&dir);
        let last = bytes.len() - 1;
        bytes[last] ^= 0x10;
        assert!(load_err(&path, &bytes).contains("checksum mismatch"));
    }

    #[test]
    fn malformed_payload_with_a_valid_checksum() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.ckpt");
        // A string length far beyond the payload: well-framed, but not a Checkpoint.
        let payload = [0xFF, 0xFF, 0xFF, 0x0F, b'x'];
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
        bytes.extend_from_slice(&payload);
        assert!(load_err(&path, &bytes).contains("malformed payload"));
    }

    #[test]
    fn duplicate_section_names_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dup.ckpt");
        let mut checkpoint = sample();
        checkpoint.sections.push(Section {
            name: "params".into(),
            bytes: vec![9],
        });
        let message = save(&path, &checkpoint).unwrap_err().to_string();
        assert!(
            message.contains("two sections are named `params`"),
            "{message}"
        );
        assert!(!path.exists());
    }
}
