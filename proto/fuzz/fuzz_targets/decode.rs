//! Every decoder of nephele-proto on arbitrary bytes (the farm's frames and payloads, the
//! viewers' pose messages): none may panic, allocate beyond the frame limit, or accept a
//! message that does not survive a re-encode.
#![no_main]

use bytes::BytesMut;
use libfuzzer_sys::fuzz_target;
use nephele_proto::pose::Pose;
use nephele_proto::stream::FrameCodec;
use nephele_proto::{FrameConfig, FrameReader, decode_frame, decode_payload, encode_frame};
use tokio_util::codec::Decoder;

fuzz_target!(|data: &[u8]| {
    let cfg = FrameConfig { max_frame: 1 << 20 };

    // Frames in memory, back to back; every valid message round-trips.
    let mut rest = data;
    while let Ok((incoming, after)) = decode_frame(rest, &cfg) {
        if let Ok(message) = incoming {
            let mut out = Vec::new();
            encode_frame(&message, &mut out, &cfg).expect("a decoded, valid message re-encodes");
            let (again, tail) = decode_frame(&out, &cfg).expect("and decodes again");
            assert!(tail.is_empty());
            assert_eq!(again, Ok(message));
        }
        rest = after;
    }

    // A payload on its own (tag byte first).
    let _ = decode_payload(data);

    // A viewer's pose message (the data channel's binary format): a pose that decodes
    // re-encodes to the same bytes.
    if let Ok(pose) = Pose::decode(data) {
        assert_eq!(pose.encode(), data, "a decoded pose re-encodes to its bytes");
    }

    // The blocking reader.
    let mut reader = FrameReader::new(std::io::Cursor::new(data), cfg);
    while reader.read_message().is_ok() {}

    // The tokio codec, fed in two pieces.
    let mut codec = FrameCodec::new(cfg);
    let split = data.len() / 2;
    let mut buf = BytesMut::from(&data[..split]);
    while let Ok(Some(_)) = codec.decode(&mut buf) {}
    buf.extend_from_slice(&data[split..]);
    while let Ok(Some(_)) = codec.decode(&mut buf) {}
    let _ = codec.decode_eof(&mut buf);
});
