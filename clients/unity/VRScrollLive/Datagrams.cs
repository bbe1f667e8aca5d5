// The live service's binary datagrams (protocol 4, docs/live.md "Datagrams"): a pose or pen sample out, a pen's
// reply in. Little-endian on the wire whatever the machine; nothing beyond the .NET base library.
using System;
using System.Collections.Generic;

namespace VRScroll.Live
{
    public static class Datagrams
    {
        public const int SampleBytes = 152;
        public const int PenReplyBytes = 104;
        public const byte Pose = 1, Pen = 2, PenRedirected = 3;  // the kind byte
        const byte HasT = 1, HasDevice = 2, Within = 2;  // flags

        /// A sample: kind Pose or Pen, the welcome's session as its 16 bytes, seq, t_s (s, this client's clock),
        /// position mm, quaternion w first; a pen may carry the tracked device's pose (both null otherwise).
        public static byte[] EncodeSample(byte kind, byte[] session, long seq, double tS, double[] position, double[] quat,
                                          double[] devicePosition, double[] deviceQuat)
        {
            var b = new byte[SampleBytes];
            b[0] = (byte)'V';
            b[1] = (byte)'S';
            b[2] = (byte)LiveClient.ProtocolVersion;
            b[3] = kind;
            b[4] = (byte)(HasT | (devicePosition != null ? HasDevice : 0));
            Buffer.BlockCopy(session, 0, b, 8, 16);
            PutLong(b, 24, seq);
            PutDouble(b, 32, tS);
            for (int k = 0; k < 3; k++) PutDouble(b, 40 + 8 * k, position[k]);
            for (int k = 0; k < 4; k++) PutDouble(b, 64 + 8 * k, quat[k]);
            if (devicePosition != null)
            {
                for (int k = 0; k < 3; k++) PutDouble(b, 96 + 8 * k, devicePosition[k]);
                for (int k = 0; k < 4; k++) PutDouble(b, 120 + 8 * k, deviceQuat[k]);
            }
            return b;
        }

        /// A pen's reply as the fields docs/live.md names (numbers double, arrays List<object>, as Json gives them);
        /// FormatException if it is not one.
        public static Dictionary<string, object> DecodePenReply(byte[] b)
        {
            if (b.Length != PenReplyBytes || b[0] != 'V' || b[1] != 'S' || b[3] != PenRedirected)
                throw new FormatException("a reply of " + b.Length + " bytes that is not a pen's");
            int flags = b[4];
            return new Dictionary<string, object> {
                { "type", "pen_redirected" }, { "seq", (double)GetLong(b, 8) },
                { "t_s", (flags & HasT) != 0 ? (object)GetDouble(b, 16) : null },
                { "position_mm", Doubles(b, 24, 3) }, { "quat_wxyz", Doubles(b, 48, 4) },
                { "offset_mm", GetDouble(b, 80) }, { "rotation_deg", GetDouble(b, 88) }, { "height_mm", GetDouble(b, 96) },
                { "flap", (double)b[5] }, { "within_thresholds", (flags & Within) != 0 } };
        }

        /// The welcome's session (32 hex digits) as the 16 bytes a sample carries.
        public static byte[] SessionBytes(string hex)
        {
            if (hex == null || hex.Length != 32) throw new FormatException("a session is 32 hex digits");
            var b = new byte[16];
            for (int k = 0; k < 16; k++) b[k] = Convert.ToByte(hex.Substring(2 * k, 2), 16);
            return b;
        }

        static List<object> Doubles(byte[] b, int at, int n)
        {
            var list = new List<object>(n);
            for (int k = 0; k < n; k++) list.Add(GetDouble(b, at + 8 * k));
            return list;
        }

        static void PutLong(byte[] b, int at, long v)
        {
            for (int k = 0; k < 8; k++) b[at + k] = (byte)(v >> (8 * k));
        }

        static void PutDouble(byte[] b, int at, double v)
        {
            PutLong(b, at, BitConverter.DoubleToInt64Bits(v));
        }

        static long GetLong(byte[] b, int at)
        {
            long v = 0;
            for (int k = 7; k >= 0; k--) v = (v << 8) | b[at + k];
            return v;
        }

        static double GetDouble(byte[] b, int at)
        {
            return BitConverter.Int64BitsToDouble(GetLong(b, at));
        }
    }
}
